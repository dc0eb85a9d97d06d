"""One generic embodied environment and the small task objects it runs (the dm_control habit).

:class:`TaskEnv` owns everything tasks share: the homes (scene, collision map, reverb probes, cached), the robot
and its sensors (RGB-D camera, binaural audio rendered continuously across steps, spectrogram, bump, odometry
pose), action checking, truncation, seeding. A :class:`Task` owns what makes a task: how an episode starts (which
home, where the robot and the sounds are), what else moves in the world (a person walking), extra observations,
reward, termination and metrics. The three navigation tasks and speaker following are tasks of this kind; the
registry (:mod:`sonicverse_core.tasks.registry`) lists them.

Agents see observations through the Gymnasium interface. Oracles (and the paper's random baseline, which stops
automatically at the goal) need privileged state: they read it through one documented channel,
``env.unwrapped.privileged()``, which returns the task's :meth:`Task.privileged` dict (for example the world, the
goals, the person). Two more channels exist for tasks that define them: ``env.unwrapped.semantic_map()`` (what a
home robot that has mapped its home knows before the episode: the floor plan, the objects and their categories, its
own start pose on that map; never where a person is) and ``env.unwrapped.report(**estimates)`` (an agent states
an estimate the task scores, e.g. where it thinks the speaker is). Nothing else in an env is an agent's business.

Actions: Box(-1, 1) of the two wheel velocities normalised to the wheel's top speed (and a stop signal for tasks
with ``stop_action``). Out-of-range values are clipped (documented); NaN, infinities or a wrong shape raise
ActionError. Episodes are truncated after ``max_steps`` steps (default: the task's, in the registry).
"""
from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, fields, replace
from functools import lru_cache

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sonicverse_core.errors import ConfigError
from sonicverse_core.tasks.episodes import DEFAULT_HOMES, SOUND_SECONDS, homes
from sonicverse_core.world.robot import wheel_action

ALL_SENSORS = ("rgb", "depth", "semantic", "audio", "spectrogram", "bump", "pose", "pointgoal")


@dataclass(frozen=True)
class TaskConfig:
    split: str = "train"
    sounds: str = "heard"  # heard | unheard
    homes: int | None = None  # first N homes of the split (default DEFAULT_HOMES[split])
    scenes: tuple | None = None  # explicit scene specs instead of the split's homes
    sensors: tuple | None = None  # None: the task's default
    width: int = 128
    height: int = 128
    hfov: float = 90.0
    depth_min: float = 0.0  # sim-to-real: 0.8
    depth_max: float = 10.0  # sim-to-real: 3.5
    step_seconds: float = 0.1
    max_steps: int | None = None  # None: the task's (registry)
    sample_rate: int = 16000
    audio_window: float = 1.0  # s of audio behind the spectrogram
    spec_pool: tuple = (4, 2)
    reverb: bool = True  # reverb probes, early reflections and late reverb
    hrtf: bool = True  # False: the robot's ears are an interaural time and level panner (no HRTF)
    occlusion: bool = True
    success_reward: float = 10.0
    step_penalty: float = 0.01
    collision_penalty: float = 0.005
    geodesic_range: tuple = (1.0, 10.0)
    sound_seconds: tuple = SOUND_SECONDS  # how long a sound plays where it stops (SemanticAudioNav)
    everlasting: bool | None = None  # the goal's sound plays all episode (None: the task's default)
    # sim-to-real
    ego_noise: float = 0.0  # RMS of the robot's ego-noise at the ears while the wheels turn at top speed
    source_gain: tuple = (1.0, 1.0)  # sampled per episode (log-uniform)
    pose_noise: tuple = (0.0, 0.0)  # random-walk std per step: (m, deg)
    home_cache: int = 8

    def __post_init__(self):
        if self.split not in DEFAULT_HOMES:
            raise ConfigError(f"unknown split '{self.split}'; use train, val or test")
        if self.sounds not in ("heard", "unheard"):
            raise ConfigError(f"sounds must be 'heard' or 'unheard', got '{self.sounds}'")
        if self.sensors is not None:
            bad = set(self.sensors) - set(ALL_SENSORS)
            if bad:
                raise ConfigError(f"unknown sensor(s) {', '.join(sorted(bad))}; use {', '.join(ALL_SENSORS)}")
        if not (0.01 <= self.step_seconds <= 1.0):
            raise ConfigError(f"step_seconds must be within 0.01-1 s, got {self.step_seconds}")
        if self.max_steps is not None and self.max_steps < 1:
            raise ConfigError("max_steps must be >= 1")
        if not (8000 <= self.sample_rate <= 48000):
            raise ConfigError(f"sample_rate must be within 8-48 kHz, got {self.sample_rate}")
        spb = self.sample_rate * self.step_seconds
        if abs(spb - round(spb)) > 1e-6:
            raise ConfigError(f"step_seconds x sample_rate must be a whole number of samples, got {spb}")
        lo, hi = self.source_gain
        if not (0 < lo <= hi):
            raise ConfigError(f"source_gain range must be positive, got {self.source_gain}")
        if self.everlasting not in (None, True, False):
            raise ConfigError(f"everlasting must be True, False or None (the task's default), got {self.everlasting!r}")
        if self.ego_noise < 0 or min(self.pose_noise) < 0:
            raise ConfigError("ego_noise and pose_noise must be >= 0")


_CONFIG_FIELDS = {f.name for f in fields(TaskConfig)}


@lru_cache(maxsize=64)
def sound_at(name: str, sample_rate: int) -> np.ndarray:
    """A sound-bank sound ('category/variant') at ``sample_rate`` (read-only, cached)."""
    from scipy.signal import resample_poly

    from assets_manifest.soundbank import SAMPLE_RATE, by_name

    x = np.asarray(by_name(name), np.float64)
    if sample_rate != SAMPLE_RATE:
        g = math.gcd(sample_rate, SAMPLE_RATE)
        x = resample_poly(x, sample_rate // g, SAMPLE_RATE // g)
    x = x.astype(np.float32)
    x.setflags(write=False)
    return x


class Home:
    """A scene with its world (collision map) and reverb probes, built once per env and kept in a small cache."""

    def __init__(self, spec: str, reverb: bool):
        from sonicverse_core.scene.spec import load_scene
        from sonicverse_core.world import World

        self.spec = spec
        self.scene = load_scene(spec)
        self.world = World(self.scene)
        self.probes = None
        if reverb:
            from sonicverse_core.acoustics.probes import scene_probes

            self.probes = scene_probes(self.scene)


class Task:
    """What makes a task; run by :class:`TaskEnv`. Override what the task needs.

    Call order per episode: ``reset`` (choose the home with ``env.use_home``, place the robot, add sounds with
    ``env.add_sound``) then, per step: the robot drives, ``advance`` (whatever else moves), the sensors render,
    ``observe`` (extra observations), ``evaluate`` (reward, termination, success). ``metrics`` when it ends.
    """

    name = "task"
    default_sensors: tuple = ("depth", "audio", "spectrogram", "bump", "pose")
    stop_action = False  # a third action component > 0 means "stop here"

    def __init__(self, cfg: TaskConfig, **options):
        if options:
            raise ConfigError(f"task {self.name} has no option(s) {', '.join(sorted(options))}")
        if cfg.everlasting is not None and not hasattr(self, "everlasting"):
            raise ConfigError(f"task {self.name} has no goal sound to make everlasting")
        self.cfg = cfg

    episode_type = None  # the task's episode record (a JsonRecord dataclass)

    def observation_spaces(self, env) -> dict:
        """Extra observation spaces (beyond the shared sensors)."""
        return {}

    def sample_episode(self, env, rng: np.random.Generator):  # pragma: no cover - interface
        raise NotImplementedError

    def episode(self, env, rng: np.random.Generator, options: dict):
        """The episode to run: ``options["episode"]`` (a record or its JSON) or a new one from the seed."""
        ep = options.get("episode")
        if ep is None:
            return self.sample_episode(env, rng)
        return self.episode_type.from_json(ep) if isinstance(ep, str) else ep

    def reset(self, env, rng: np.random.Generator, options: dict):  # pragma: no cover - interface
        """Start an episode; return its record (any object with ``episode_id`` and ``scene``)."""
        raise NotImplementedError

    def advance(self, env, dt: float) -> None:
        """Move what moves besides the robot (called after the robot drives, before the sensors render)."""

    def observe(self, env, obs: dict) -> None:
        """Add the task's extra observations to ``obs``."""

    def evaluate(self, env, action: np.ndarray) -> tuple[float, bool, bool]:  # pragma: no cover - interface
        """(reward, terminated, success) after a step."""
        raise NotImplementedError

    def info(self, env) -> dict:
        return {}

    def metrics(self, env, success: bool) -> dict:
        return {"success": float(success)}

    def privileged(self, env) -> dict:
        """State an oracle may read (documented per task); agents that learn or act from sensors must not."""
        return {"world": env.home.world}

    def semantic_map(self, env) -> "SemanticMap":
        """The map a robot may know before the episode (tasks that give one override this)."""
        raise ConfigError(f"task {self.name} gives agents no semantic map")

    def report(self, env, estimates: dict) -> None:
        """An agent's estimate for the task to score (tasks that score some override this)."""
        raise ConfigError(f"task {self.name} scores no estimates")


def odometry(start, pose) -> np.ndarray:
    """The ``pose`` observation: (x, y) of ``pose`` in the frame of ``start`` (x forward, y left) and the sine and
    cosine of the yaw turned since (both poses x, y, yaw degrees); :meth:`SemanticMap.to_map` inverts it."""
    a = math.radians(start[2])
    d = np.asarray(pose[:2], float) - np.asarray(start[:2], float)
    dyaw = math.radians(pose[2] - start[2])
    return np.array([math.cos(a) * d[0] + math.sin(a) * d[1], -math.sin(a) * d[0] + math.cos(a) * d[1],
                     math.sin(dyaw), math.cos(dyaw)], np.float32)


@dataclass(frozen=True)
class MapObject:
    name: str
    category: str
    position: tuple  # (x, y, z) of its centre, m
    lo: tuple  # (x, y, z) of its world-aligned bounding box
    hi: tuple
    movable: bool  # the robot can pick it up


@dataclass(frozen=True)
class SemanticMap:
    """What a home robot knows of its home before an episode, in the home's (map) frame: ``grid`` (a
    :class:`~sonicverse_core.geometry.navgrid.NavGrid` of the floor with doors, furniture and objects as they stood at
    the episode's start; read-only), ``objects`` (every object's name, category, centre and bounds), ``start`` (the
    robot's (x, y, yaw degrees) at the start: the ``pose`` observation is odometry from there). People are not on it."""

    grid: object
    objects: tuple
    start: tuple

    def to_map(self, pose_obs) -> tuple[np.ndarray, float]:
        """The ``pose`` observation (odometry from the start: x, y, sin, cos) as (x, y) and yaw degrees on the map."""
        x, y, s, c = (float(v) for v in pose_obs)
        a = math.radians(self.start[2])
        xy = np.array([self.start[0] + math.cos(a) * x - math.sin(a) * y,
                       self.start[1] + math.sin(a) * x + math.cos(a) * y])
        yaw = (self.start[2] + math.degrees(math.atan2(s, c)) + 180.0) % 360.0 - 180.0
        return xy, yaw

    @classmethod
    def of(cls, world, start) -> "SemanticMap":
        objs = []
        for o in world.scene.objects:
            b = o.world_bounds()
            objs.append(MapObject(o.name, o.category, tuple(float(v) for v in o.position), tuple(map(float, b[0])),
                                  tuple(map(float, b[1])), bool(o.movable)))
        return cls(world.grid, tuple(objs), tuple(float(v) for v in start))


class TaskEnv(gym.Env):
    """The one embodied environment: ``TaskEnv(task="AudioGoal", **config_fields_and_task_options)``.

    Keyword arguments that are :class:`TaskConfig` fields configure the env; any others go to the task's
    constructor (for example ``person_speed`` for speaker following)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, task: str = "AudioGoal", render_mode: str | None = None, config: TaskConfig | None = None,
                 **kwargs):
        from sonicverse_core.tasks.registry import task_spec
        from sonicverse_core.world import RobotConfig

        self.spec_entry = spec = task_spec(task)
        if spec.kind != "embodied":
            raise ConfigError(f"task '{spec.cli}' has no robot env; run it with `sonicverse task run {spec.cli}`")
        cfg_kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in kwargs.items() if k in _CONFIG_FIELDS}
        task_kw = {k: v for k, v in kwargs.items() if k not in _CONFIG_FIELDS}
        cfg = replace(config or TaskConfig(), **cfg_kw)
        if cfg.max_steps is None:
            cfg = replace(cfg, max_steps=spec.max_steps)
        self.cfg = cfg
        self.task: Task = spec.load()(cfg, **task_kw)
        self.TASK = spec.name
        if render_mode not in (None, "rgb_array"):
            raise ConfigError(f"render_mode must be None or 'rgb_array', got '{render_mode}'")
        self.render_mode = render_mode
        self.sensors = tuple(cfg.sensors) if cfg.sensors is not None else self.task.default_sensors
        self.scene_specs = list(cfg.scenes) if cfg.scenes else homes(cfg.split, cfg.homes)
        self.robot = RobotConfig()
        self.spb = int(round(cfg.sample_rate * cfg.step_seconds))
        self.sub_blocks = next(k for k in range(1, self.spb + 1) if self.spb % k == 0 and self.spb // k <= 4096)
        self.audio_n = max(int(round(cfg.audio_window * cfg.sample_rate)), 400)
        from sonicverse_core.sensors.audio import HOP, BinauralWindow, Spectrogram, StreamingSpectrogram

        # the spectrogram as a stream when the window and the step are whole hops (the defaults); otherwise the
        # full STFT over a rolling window of the last audio_window seconds
        self._window = None
        if self.audio_n % HOP == 0 and self.spb % HOP == 0:
            self._spec = StreamingSpectrogram(self.audio_n, cfg.spec_pool)
        else:
            self._spec = Spectrogram(self.audio_n, cfg.spec_pool)
            self._window = BinauralWindow(self.audio_n)
        self.last_audio = np.zeros((2, self.spb), np.float32)  # what the robot heard in the last step
        # the robot's ears are rendered only where something hears them: an audio sensor, or a caller that keeps
        # last_audio (``eval --video``) and sets ``hear``. Without them the steps are the same, step for step
        # (nothing random is drawn for the audio), and last_audio stays silent
        self.hear = "audio" in self.sensors or "spectrogram" in self.sensors
        n_act = 3 if self.task.stop_action else 2
        self.action_space = spaces.Box(-1.0, 1.0, (n_act,), np.float32)
        obs = {}
        H, W = cfg.height, cfg.width
        if "rgb" in self.sensors:
            obs["rgb"] = spaces.Box(0, 255, (H, W, 3), np.uint8)
        if "depth" in self.sensors:
            obs["depth"] = spaces.Box(0.0, cfg.depth_max, (H, W, 1), np.float32)
        if "semantic" in self.sensors:  # category ids (sonicverse_core.sensors.camera.CLASSES first, fixed)
            obs["semantic"] = spaces.Box(0, 65535, (H, W, 1), np.int32)
        if "audio" in self.sensors:
            obs["audio"] = spaces.Box(-1.0, 1.0, (2, self.spb), np.float32)
        if "spectrogram" in self.sensors:
            obs["spectrogram"] = spaces.Box(0.0, 20.0, self._spec.shape, np.float32)  # log1p(|STFT|) <= log1p(400)
        if "bump" in self.sensors:
            obs["bump"] = spaces.Box(0.0, 1.0, (1,), np.float32)
        if "pose" in self.sensors:
            obs["pose"] = spaces.Box(-1000.0, 1000.0, (4,), np.float32)
        obs.update(self.task.observation_spaces(self))
        self.observation_space = spaces.Dict(obs)
        self._homes: OrderedDict[str, Home] = OrderedDict()
        self.camera = None
        self.episode = None
        self.home: Home | None = None
        self.renderer = None
        self.source = None  # the episode's main sound source (the target's or the person's voice)
        self._count = 0
        self._ego = None
        self._actors: dict[str, tuple] = {}  # name -> (trimesh, rgba): bodies the camera sees (a person)

    # --- for tasks --------------------------------------------------------------------------------------------
    def use_home(self, spec: str) -> Home:
        """The home of this episode (cached), every door and object back where the scene started."""
        h = self._homes.get(spec)
        if h is None:
            h = self._homes[spec] = Home(spec, self.cfg.reverb)
            while len(self._homes) > max(1, self.cfg.home_cache):
                self._homes.popitem(last=False)
        self._homes.move_to_end(spec)
        h.world.restore()
        self.home = h
        return h

    def new_renderer(self) -> None:
        """A fresh acoustic renderer for the episode (tasks then add their sounds)."""
        from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig

        c = self.cfg
        rc = RenderConfig(sample_rate=c.sample_rate, block=self.spb // self.sub_blocks, occlusion=c.occlusion,
                          output="binaural" if c.hrtf else "stereo",
                          early_reflections=c.reverb, late_reverb=c.reverb)
        self.renderer = AcousticRenderer(self.home.scene, rc, self.home.probes)

    def add_sound(self, signal: np.ndarray, **kwargs):
        """A source in this episode's renderer (``AcousticRenderer.add_source`` arguments)."""
        return self.renderer.add_source(signal, **kwargs)

    def add_actor(self, name: str, mesh, rgba=None) -> None:
        """A body the robot's camera sees (moved with :meth:`move_actor`); not part of the scene's acoustics.
        ``rgba``: one colour for all of it (None: the mesh's own face colours)."""
        self._actors[name] = (mesh, rgba, np.eye(4))
        if self.camera is not None:
            self.camera.set_actor(name, mesh, rgba)

    def move_actor(self, name: str, pose: np.ndarray) -> None:
        mesh, rgba, _ = self._actors[name]
        self._actors[name] = (mesh, rgba, np.asarray(pose, float))

    def privileged(self) -> dict:
        """The documented channel for privileged state (oracles only): the task's :meth:`Task.privileged`."""
        if self.episode is None:
            raise ConfigError("call reset() before privileged()")
        return self.task.privileged(self)

    def semantic_map(self) -> SemanticMap:
        """The task's :class:`SemanticMap` of this episode's home (tasks that give one)."""
        if self.episode is None:
            raise ConfigError("call reset() before semantic_map()")
        return self.task.semantic_map(self)

    def report(self, **estimates) -> None:
        """Give the task an estimate to score (tasks that score some: see the task's docstring)."""
        if self.episode is None or self._done:
            raise ConfigError("report() belongs to a running episode")
        self.task.report(self, estimates)

    # --- sensors ----------------------------------------------------------------------------------------------
    def _camera(self):
        if self.camera is None:
            from sonicverse_core.sensors.camera import RGBDCamera

            c = self.cfg
            self.camera = RGBDCamera(self.home.scene, c.width, c.height, c.hfov, c.depth_min, c.depth_max,
                                     rgb="rgb" in self.sensors or self.render_mode == "rgb_array",
                                     depth="depth" in self.sensors, semantic="semantic" in self.sensors)
        self.camera.set_scene(self.home.scene)
        for name, (mesh, rgba, pose) in self._actors.items():
            self.camera.set_actor(name, mesh, rgba)
            self.camera.move_actor(name, pose)
        return self.camera

    def _render_audio(self) -> np.ndarray:
        w = self.home.world
        self.renderer.set_listener(self.listener, w.ears, w.pose[2])
        blocks = [self.renderer.render_block()[0] for _ in range(self.sub_blocks)]
        out = blocks[0] if len(blocks) == 1 else np.concatenate(blocks, axis=1)
        out = out.astype(np.float32, copy=False)
        if self.cfg.ego_noise > 0:
            level = self.cfg.ego_noise * float(np.mean(np.abs(self._last_wheels)))
            if level > 0:
                idx = (self._ego_pos + np.arange(self.spb)) % len(self._ego)
                idx2 = (idx + 7919) % len(self._ego)  # the two microphones hear decorrelated noise
                out = out + level * np.stack([self._ego[idx], self._ego[idx2]])
                np.clip(out, -1.0, 1.0, out=out)
            self._ego_pos = (self._ego_pos + self.spb) % len(self._ego)
        return out

    def _observe(self) -> dict:
        w = self.home.world
        obs = {}
        if self.hear:
            block = self.last_audio = self._render_audio()
            if self._window is not None:
                self._window.push(block)
            if "audio" in self.sensors:
                obs["audio"] = block.copy()
            if "spectrogram" in self.sensors:
                obs["spectrogram"] = (self._spec(self._window.buf) if self._window is not None
                                      else self._spec.push(block))
        if "rgb" in self.sensors or "depth" in self.sensors or "semantic" in self.sensors:
            img = self._camera().render(*w.camera)
            if "rgb" in self.sensors:
                obs["rgb"] = img["rgb"]
            if "depth" in self.sensors:
                obs["depth"] = img["depth"][..., None]
            if "semantic" in self.sensors:
                obs["semantic"] = img["semantic"][..., None]
        if "bump" in self.sensors:
            obs["bump"] = np.array([1.0 if w.bumped else 0.0], np.float32)
        sn = self.cfg.pose_noise
        if sn[0] > 0 or sn[1] > 0:
            self._pose_err += self._noise_rng.normal(0.0, 1.0, 3) * np.array([sn[0], sn[0], sn[1]])
        self.sensed_pose = pose = w.pose + self._pose_err
        if "pose" in self.sensors:
            obs["pose"] = odometry(self._start, pose)
        self.task.observe(self, obs)
        return obs

    def _info(self) -> dict:
        return {"episode_id": self.episode.episode_id, "steps": self.steps, "collisions": self.collisions,
                "path_length": self.path_length, "success": False, "is_success": False, **self.task.info(self)}

    # --- gym API ----------------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        rng = self.np_random
        self._actors = {}
        if self.camera is not None:
            self.camera.clear_actors()
        ep = self.task.reset(self, rng, dict(options or {}))
        self._noise_rng = np.random.default_rng(rng.integers(2 ** 63))
        self._pose_err = np.zeros(3)
        if not ep.episode_id:
            eid = f"{self.cfg.split}/{seed}" if seed is not None else f"{self.cfg.split}/#{self._count}"
            ep = replace(ep, episode_id=eid)
        self._count += 1
        self.episode = ep
        w = self.home.world
        self._start = w.pose.copy()
        self.steps, self.collisions, self.path_length = 0, 0, 0.0
        self._done = False
        self.listener = self.renderer.add_listener(w.ears, yaw=w.pose[2])
        if self.cfg.ego_noise > 0:
            from sonicverse_core.sensors.audio import ego_noise

            if self._ego is None:
                self._ego = ego_noise(30.0, self.cfg.sample_rate, np.random.default_rng(0xE60))
            self._ego_pos = int(self._noise_rng.integers(len(self._ego)))
        if self._window is None:
            self._spec.reset()
        else:
            self._window.clear()
        self._last_wheels = np.zeros(2)
        obs = self._observe()
        return obs, self._info()

    def step(self, action):
        if self.episode is None or self._done:
            raise ConfigError("call reset() before step() (and after an episode ends)")
        a = wheel_action(action, self.action_space.shape[0])
        w = self.home.world
        self._last_wheels = a[:2]
        moved = w.drive(a[:2], self.cfg.step_seconds)
        self.steps += 1
        self.path_length += moved
        self.collisions += int(w.bumped)
        self.task.advance(self, self.cfg.step_seconds)
        obs = self._observe()
        reward, terminated, success = self.task.evaluate(self, a)
        truncated = not terminated and self.steps >= self.cfg.max_steps
        info = self._info()
        info["success"] = info["is_success"] = bool(success)  # is_success: the key SB3 and others read
        if terminated or truncated:
            self._done = True
            info["metrics"] = self.task.metrics(self, bool(success))
        return obs, float(reward), bool(terminated), bool(truncated), info

    def metrics(self, success: bool) -> dict:
        return self.task.metrics(self, success)

    def render(self):
        if self.render_mode != "rgb_array" or self.home is None:
            return None
        return self._camera().render(*self.home.world.camera).get("rgb")

    def close(self):
        if self.camera is not None:
            self.camera.close()
            self.camera = None
        super().close()
