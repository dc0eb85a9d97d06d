"""Gymnasium environments for audio-visual navigation with a TurtleBot in a household scene.

``Sonicverse/AudioGoal-v0``: go to the sounding object (depth + binaural audio); the episode succeeds as soon as
the robot is within 0.36 m of one of the nine terminal positions.
``Sonicverse/AudioPointGoal-v0``: the same with a GPS + compass pointer to the goal.
``Sonicverse/SemanticAudioNav-v0``: the paper's task: RGB + depth + audio; the sound stops after a while; a third
action component > 0 is the stop signal, and only a stop within 0.36 m of a terminal position succeeds.

Actions: Box(-1, 1) of the two wheel velocities normalised to the wheel's top speed (and the stop signal).
Out-of-range values are clipped (documented); NaN, infinities or a wrong shape raise ActionError.
Reward: geodesic progress (m) + ``success_reward`` on success - ``step_penalty`` per step - ``collision_penalty``
per step with a bump. Episodes are truncated after ``max_steps`` steps.
"""
from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, replace
from functools import lru_cache

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from sonicverse_core.errors import ConfigError
from sonicverse_core.tasks.episodes import (DEFAULT_HOMES, SOUND_SECONDS, SUCCESS_RADIUS, Episode, homes,
                                            sample_episode)
from sonicverse_core.tasks.metrics import shortest_actions, sna, soft_spl, spl
from sonicverse_core.world.robot import wheel_action

ALL_SENSORS = ("rgb", "depth", "audio", "spectrogram", "bump", "pose", "pointgoal")


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
    max_steps: int = 500
    sample_rate: int = 16000
    audio_window: float = 1.0  # s of audio behind the spectrogram
    spec_pool: tuple = (4, 2)
    reverb: bool = True  # reverb probes, early reflections and late reverb
    occlusion: bool = True
    success_reward: float = 10.0
    step_penalty: float = 0.01
    collision_penalty: float = 0.005
    geodesic_range: tuple = (1.0, 10.0)
    sound_seconds: tuple = SOUND_SECONDS
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
        if self.max_steps < 1:
            raise ConfigError("max_steps must be >= 1")
        if not (8000 <= self.sample_rate <= 48000):
            raise ConfigError(f"sample_rate must be within 8-48 kHz, got {self.sample_rate}")
        spb = self.sample_rate * self.step_seconds
        if abs(spb - round(spb)) > 1e-6:
            raise ConfigError(f"step_seconds x sample_rate must be a whole number of samples, got {spb}")
        lo, hi = self.source_gain
        if not (0 < lo <= hi):
            raise ConfigError(f"source_gain range must be positive, got {self.source_gain}")
        if self.ego_noise < 0 or min(self.pose_noise) < 0:
            raise ConfigError("ego_noise and pose_noise must be >= 0")


@lru_cache(maxsize=64)
def _sound_at(name: str, sample_rate: int) -> np.ndarray:
    from scipy.signal import resample_poly

    from assets_manifest.soundbank import SAMPLE_RATE, by_name

    x = np.asarray(by_name(name), np.float64)
    if sample_rate != SAMPLE_RATE:
        g = math.gcd(sample_rate, SAMPLE_RATE)
        x = resample_poly(x, sample_rate // g, SAMPLE_RATE // g)
    x = x.astype(np.float32)
    x.setflags(write=False)
    return x


class _Home:
    """A scene with its world (collision map) and reverb probes, built once per env and kept in a small cache."""

    def __init__(self, spec: str, reverb: bool):
        from sonicverse_core.scene.spec import load_scene
        from sonicverse_core.world import World

        self.scene = load_scene(spec)
        self.world = World(self.scene)
        self.probes = None
        if reverb:
            from sonicverse_core.acoustics.probes import scene_probes

            self.probes = scene_probes(self.scene)


class SonicverseNavEnv(gym.Env):
    """Base environment; the task variants set ``TASK``, the default sensors and the stop signal."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}
    TASK = "AudioGoal"
    DEFAULT_SENSORS = ("depth", "audio", "spectrogram", "bump", "pose")
    STOP_ACTION = False

    def __init__(self, render_mode: str | None = None, config: TaskConfig | None = None, **kwargs):
        cfg = config or TaskConfig()
        if kwargs:
            cfg = replace(cfg, **{k: (tuple(v) if isinstance(v, list) else v) for k, v in kwargs.items()})
        self.cfg = cfg
        if render_mode not in (None, "rgb_array"):
            raise ConfigError(f"render_mode must be None or 'rgb_array', got '{render_mode}'")
        self.render_mode = render_mode
        self.sensors = tuple(cfg.sensors) if cfg.sensors is not None else self.DEFAULT_SENSORS
        self.scene_specs = list(cfg.scenes) if cfg.scenes else homes(cfg.split, cfg.homes)
        from sonicverse_core.world import RobotConfig

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
        n_act = 3 if self.STOP_ACTION else 2
        self.action_space = spaces.Box(-1.0, 1.0, (n_act,), np.float32)
        obs = {}
        H, W = cfg.height, cfg.width
        if "rgb" in self.sensors:
            obs["rgb"] = spaces.Box(0, 255, (H, W, 3), np.uint8)
        if "depth" in self.sensors:
            obs["depth"] = spaces.Box(0.0, cfg.depth_max, (H, W, 1), np.float32)
        if "audio" in self.sensors:
            obs["audio"] = spaces.Box(-1.0, 1.0, (2, self.spb), np.float32)
        if "spectrogram" in self.sensors:
            obs["spectrogram"] = spaces.Box(0.0, 20.0, self._spec.shape, np.float32)  # log1p(|STFT|) <= log1p(400)
        if "bump" in self.sensors:
            obs["bump"] = spaces.Box(0.0, 1.0, (1,), np.float32)
        if "pose" in self.sensors:
            obs["pose"] = spaces.Box(-1000.0, 1000.0, (4,), np.float32)
        if "pointgoal" in self.sensors:
            obs["pointgoal"] = spaces.Box(-1000.0, 1000.0, (3,), np.float32)
        self.observation_space = spaces.Dict(obs)
        self._homes: OrderedDict[str, _Home] = OrderedDict()
        self.camera = None
        self.episode: Episode | None = None
        self.home: _Home | None = None
        self._count = 0
        self._ego = None

    # --- homes and sensors ------------------------------------------------------------------------------------
    def _home(self, spec: str) -> _Home:
        h = self._homes.get(spec)
        if h is None:
            h = self._homes[spec] = _Home(spec, self.cfg.reverb)
            while len(self._homes) > max(1, self.cfg.home_cache):
                self._homes.popitem(last=False)
        self._homes.move_to_end(spec)
        return h

    def _camera(self):
        if self.camera is None:
            from sonicverse_core.sensors.camera import RGBDCamera

            c = self.cfg
            self.camera = RGBDCamera(self.home.scene, c.width, c.height, c.hfov, c.depth_min, c.depth_max,
                                     rgb="rgb" in self.sensors or self.render_mode == "rgb_array",
                                     depth="depth" in self.sensors)
        self.camera.set_scene(self.home.scene)
        return self.camera

    def sample_episode(self, rng: np.random.Generator) -> Episode:
        c = self.cfg
        for _ in range(50):
            spec = self.scene_specs[int(rng.integers(len(self.scene_specs)))]
            home = self._home(spec)
            home.world.restore()
            ep = sample_episode(home.world, spec, c.split, c.sounds, rng, episode_id="",
                                geodesic_range=c.geodesic_range, sound_seconds=c.sound_seconds)
            if ep is not None:
                lo, hi = c.source_gain
                gain = float(math.exp(rng.uniform(math.log(lo), math.log(hi)))) if hi > lo else float(lo)
                return replace(ep, source_gain=gain)
        raise ConfigError("no valid episode could be sampled in these homes (geodesic range too strict?)")

    # --- gym API ----------------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        rng = self.np_random
        options = options or {}
        ep = options.get("episode")
        if ep is None:
            ep = self.sample_episode(rng)
            eid = f"{self.cfg.split}/{seed}" if seed is not None else f"{self.cfg.split}/#{self._count}"
            ep = replace(ep, episode_id=eid)
        elif isinstance(ep, str):
            ep = Episode.from_json(ep)
        self._count += 1
        self.episode = ep
        self.home = self._home(ep.scene)
        world = self.home.world
        world.restore()
        world.place_robot(*ep.start)
        self._noise_rng = np.random.default_rng(rng.integers(2 ** 63))
        self._pose_err = np.zeros(3)
        self._start = np.array(ep.start, float)
        goals = np.array(ep.goals, float)
        self._goals = goals
        self._field = world.grid.distance_field(goals)
        self._geo0 = self._geodesic()
        self._prev_geo = self._geo0
        self.steps, self.collisions, self.path_length = 0, 0, 0.0
        self._done = False
        self._setup_audio(ep)
        if self._window is None:
            self._spec.reset()
        else:
            self._window.clear()
        self._last_wheels = np.zeros(2)
        obs = self._observe()
        return obs, self._info()

    def _setup_audio(self, ep: Episode) -> None:
        from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig

        c = self.cfg
        rc = RenderConfig(sample_rate=c.sample_rate, block=self.spb // self.sub_blocks, occlusion=c.occlusion,
                          early_reflections=c.reverb, late_reverb=c.reverb)
        self.renderer = AcousticRenderer(self.home.scene, rc, self.home.probes)
        base = _sound_at(ep.sound, c.sample_rate)
        n = int(ep.sound_seconds * c.sample_rate)
        sig = np.resize(base, n) if n > 0 else base[:1] * 0
        self.source = self.renderer.add_source(sig, loop=False, gain=ep.source_gain, attached_to=ep.object_name)
        w = self.home.world
        self.listener = self.renderer.add_listener(w.ears, yaw=w.pose[2])
        if c.ego_noise > 0:
            from sonicverse_core.sensors.audio import ego_noise

            if self._ego is None:
                self._ego = ego_noise(30.0, c.sample_rate, np.random.default_rng(0xE60))
            self._ego_pos = int(self._noise_rng.integers(len(self._ego)))

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

    def _geodesic(self) -> float:
        w = self.home.world
        return float(w.grid.geodesic_from_field(self._field, w.pose[None, :2])[0])

    def _euclid_to_goal(self) -> float:
        return float(np.min(np.linalg.norm(self._goals - self.home.world.pose[:2], axis=1)))

    def at_goal(self) -> bool:
        return self._euclid_to_goal() <= SUCCESS_RADIUS

    def _observe(self) -> dict:
        w = self.home.world
        obs = {}
        block = self.last_audio = self._render_audio()
        if self._window is not None:
            self._window.push(block)
        if "audio" in self.sensors:
            obs["audio"] = block.copy()
        if "spectrogram" in self.sensors:
            obs["spectrogram"] = self._spec(self._window.buf) if self._window is not None else self._spec.push(block)
        if "rgb" in self.sensors or "depth" in self.sensors:
            img = self._camera().render(*w.camera)
            if "rgb" in self.sensors:
                obs["rgb"] = img["rgb"]
            if "depth" in self.sensors:
                obs["depth"] = img["depth"][..., None]
        if "bump" in self.sensors:
            obs["bump"] = np.array([1.0 if w.bumped else 0.0], np.float32)
        sn = self.cfg.pose_noise
        if sn[0] > 0 or sn[1] > 0:
            self._pose_err += self._noise_rng.normal(0.0, 1.0, 3) * np.array([sn[0], sn[0], sn[1]])
        pose = w.pose + self._pose_err
        if "pose" in self.sensors:
            a = math.radians(self._start[2])
            d = pose[:2] - self._start[:2]
            dx, dy = math.cos(a) * d[0] + math.sin(a) * d[1], -math.sin(a) * d[0] + math.cos(a) * d[1]
            dyaw = math.radians(pose[2] - self._start[2])
            obs["pose"] = np.array([dx, dy, math.sin(dyaw), math.cos(dyaw)], np.float32)
        if "pointgoal" in self.sensors:
            g = self._goals[int(np.argmin(np.linalg.norm(self._goals - w.pose[:2], axis=1)))]
            d = g - pose[:2]
            bearing = math.atan2(d[1], d[0]) - math.radians(pose[2])
            obs["pointgoal"] = np.array([math.hypot(*d), math.cos(bearing), math.sin(bearing)], np.float32)
        return obs

    def _info(self) -> dict:
        return {"episode_id": self.episode.episode_id, "distance_to_goal": self._prev_geo, "at_goal": self.at_goal(),
                "steps": self.steps, "collisions": self.collisions, "path_length": self.path_length,
                "success": False, "is_success": False}

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
        obs = self._observe()
        geo = self._geodesic()
        reached = self.at_goal()
        stop = bool(self.STOP_ACTION and a[2] > 0)
        success = reached and (stop or not self.STOP_ACTION)
        terminated = success or stop
        truncated = not terminated and self.steps >= self.cfg.max_steps
        c = self.cfg
        reward = (self._prev_geo - geo if np.isfinite(geo) and np.isfinite(self._prev_geo) else 0.0)
        reward += c.success_reward * success - c.step_penalty - c.collision_penalty * w.bumped
        self._prev_geo = geo
        info = self._info()
        info["success"] = info["is_success"] = success  # is_success: the key SB3 and others read
        if terminated or truncated:
            self._done = True
            info["metrics"] = self.metrics(success)
        return obs, float(reward), terminated, truncated, info

    def metrics(self, success: bool) -> dict:
        l, p = self._geo0, self.path_length
        n_star = shortest_actions(l, self.robot.max_speed, self.cfg.step_seconds)
        return {"success": float(success), "spl": spl(success, l, p), "sna": sna(success, n_star, self.steps),
                "soft_spl": soft_spl(l, p, self._prev_geo), "distance_to_goal": self._prev_geo, "geodesic": l,
                "path_length": p, "steps": self.steps, "n_star": n_star, "collisions": self.collisions}

    def render(self):
        if self.render_mode != "rgb_array" or self.home is None:
            return None
        return self._camera().render(*self.home.world.camera).get("rgb")

    def close(self):
        if self.camera is not None:
            self.camera.close()
            self.camera = None
        super().close()


class AudioGoalEnv(SonicverseNavEnv):
    TASK = "AudioGoal"


class AudioPointGoalEnv(SonicverseNavEnv):
    TASK = "AudioPointGoal"
    DEFAULT_SENSORS = ("depth", "audio", "spectrogram", "bump", "pose", "pointgoal")


class SemanticAudioNavEnv(SonicverseNavEnv):
    TASK = "SemanticAudioNav"
    DEFAULT_SENSORS = ("rgb", "depth", "audio", "spectrogram", "bump", "pose")
    STOP_ACTION = True


TASKS = {"AudioGoal": AudioGoalEnv, "AudioPointGoal": AudioPointGoalEnv, "SemanticAudioNav": SemanticAudioNavEnv}
