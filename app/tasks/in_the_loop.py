"""The human-robot tasks in the VR loop: the person is the user.

Each is a :class:`~app.tasks.roam.FrameTask` (named by the task registry's ``frame_task``), so it runs unchanged
under the OpenVR, desktop and headless backends, with live or offline audio:

* :class:`FollowMe` (speaker following): the user walks and talks; the robot's agent follows from what reaches its
  ears (and its camera).
* :class:`FetchForMe` (voice retrieval): the user asks for an object the robot can carry; the robot's agent
  understands it from its ears, fetches one and puts it down by the user.
* :class:`OrientationTrials` (auditory orientation training, audio only, no robot): a sound plays from a place
  around the user, who turns to face it (turn trials) or walks to it (walk trials) and pulls the right trigger.

The robot's agent is the one ``sonicverse task run`` uses (:func:`agents.make_agent`): every ``STEP`` (0.1 s) of
frame time it gets the observations the Gymnasium env would give it (binaural audio at the robot's ears, resampled
to the env's 16 kHz, and their spectrogram for agents that learned on it; depth from the robot's camera, at the size
a learned agent was trained on, when views are on; bump; odometry pose) and its action drives
the robot's wheels until the next step. What the agent may read besides (``privileged`` for oracles, the
``semantic_map``, ``report``) goes through :class:`LoopEnv`, which stands in for the env.

In the headless backend the user is simulated (:meth:`headless_input`): a walker who talks (following), a person
who stands and asks (retrieval; their voice is espeak-ng), a listener model who turns or walks (orientation). With
``--audio live`` the user's voice is the microphone; offline it is synthesised. Each task's :meth:`summary` holds
the task's metrics (the registry's keys) for the session.
"""
from __future__ import annotations

import math

import numpy as np

from app.tasks.roam import FrameTask
from app.vr.frame import BUTTON_TRIGGER, RIGHT, FrameInput
from sonicverse_core.errors import ConfigError

STEP = 0.1  # s: the agent's step (the env's step_seconds)
ENV_RATE = 16_000  # Hz: the env's audio rate (the agents' filters and recogniser expect it)


class LoopEnv:
    """What an agent's ``reset`` reads from an env, for an agent in the VR loop."""

    def __init__(self, task: "RobotInTheLoop", session, n_actions: int):
        from gymnasium import spaces

        from sonicverse_core.tasks.base import TaskConfig

        self.task, self.session = task, session
        self.cfg = TaskConfig(step_seconds=STEP, sample_rate=ENV_RATE)
        self.robot = session.world.robot
        self.action_space = spaces.Box(-1.0, 1.0, (n_actions,), np.float32)

    def privileged(self) -> dict:
        return self.task.privileged(self.session)

    def semantic_map(self):
        return self.task.semantic_map(self.session)

    def report(self, **estimates) -> None:
        self.task.report(self.session, estimates)


def _user_xy(f: FrameInput) -> np.ndarray:
    return np.array([f.head[0, 3], f.head[1, 3]], float)


class RobotInTheLoop(FrameTask):
    """A registry task's agent driving the session's robot, the user as the person (see the module's docstring)."""

    spec_name = ""
    n_actions = 2

    def __init__(self, agent: str | None = None, seed: int = 0, checkpoint=None):
        from agents import check_agent
        from sonicverse_core.tasks.registry import task_spec

        self.spec = task_spec(self.spec_name)
        self.agent_name = agent or self.spec.agents[0]
        self.checkpoint = checkpoint  # a learned agent's weights (default: the shipped ones)
        check_agent(self.agent_name, self.spec.name, checkpoint)
        self.seed = int(seed)
        self.rng = np.random.default_rng(seed)
        self.done = False
        self.name = self.spec.cli

    def audio_sources(self, scene) -> list:
        """No sounding objects besides the user's voice: the home as quiet as in the task's env."""
        return []

    # --- the loop -------------------------------------------------------------------------------------------------
    def reset(self, session) -> None:
        from agents import make_agent

        if session.world is None:
            raise ConfigError(f"{self.spec.cli} needs the robot (--robots 1)")
        w = session.world
        self.setup(session)
        self.start = w.pose.copy()
        self.env = LoopEnv(self, session, self.n_actions)
        self.agent = make_agent(self.agent_name, np.random.default_rng(self.seed), self.spec.name,
                                checkpoint=self.checkpoint)
        self._sensors(getattr(self.agent, "env_kwargs", lambda: {})())
        self.wheels = np.zeros(2)
        self.t_next, self.steps, self.collisions, self.path_length = 0.0, 0, 0, 0.0
        self.user = None
        self._obs_cache = None
        self._started = False

    def step(self, session, f: FrameInput) -> None:
        w = session.world
        self.user = _user_xy(f)
        w.bodies["person"] = (self.user.copy(), 0.22)  # the robot bumps into the user
        if not self.done and f.t + 1e-9 >= self.t_next:
            obs = self._observe(session)
            info = self.info(session)
            if not self._started:
                self.agent.reset(self.env, obs, info)
                self._started = True
            a = np.asarray(self.agent.act(obs, info), float)
            self.wheels = np.clip(a[:2], -1, 1)
            self.steps += 1
            self.t_next += STEP
            self.after_act(session, f, a)
        if self.done:
            self.wheels = np.zeros(2)
        moved = w.drive(self.wheels, f.dt)
        self.path_length += moved
        self.collisions += int(w.bumped)
        self.advance(session, f)

    def _sensors(self, kw: dict) -> None:
        """What the agent observes (a learned agent's ``env_kwargs``: its sensors and image size): the spectrogram
        is computed from the robot's ears as the env computes it (a stream over the last ``audio_window`` s)."""
        from dataclasses import replace

        c = self.env.cfg = replace(self.env.cfg, **{k: kw[k] for k in ("width", "height") if k in kw})
        self.spec_stream = None
        if "spectrogram" in kw.get("sensors", ()):
            from sonicverse_core.sensors.audio import StreamingSpectrogram

            self.spec_stream = StreamingSpectrogram(max(int(round(c.audio_window * ENV_RATE)), 400), c.spec_pool)

    def _observe(self, session) -> dict:
        from scipy.signal import resample_poly

        from app.vr.transforms import look_matrix
        from sonicverse_core.tasks.base import odometry

        w = session.world
        obs = {}
        if session.audio is not None:
            sr = session.cfg.sample_rate
            n = int(round(STEP * ENV_RATE))
            if sr == ENV_RATE:
                obs["audio"] = session.audio.last(1, n)
            else:  # resampled with 50 ms of context before and the last 2 ms held back: a block resampled on its own
                # has filter edges, which the agents' onset detectors would take for onsets at every block boundary
                x = session.audio.last(1, int(round((STEP + 0.052) * sr)))
                y = resample_poly(x, ENV_RATE, sr, axis=1)
                hold = int(round(0.002 * ENV_RATE))
                obs["audio"] = np.clip(y[:, -(n + hold):-hold], -1, 1).astype(np.float32)
        else:
            obs["audio"] = np.zeros((2, int(STEP * ENV_RATE)), np.float32)
        if self.spec_stream is not None:
            obs["spectrogram"] = self.spec_stream.push(obs["audio"])
        if session.views is not None:
            c = self.env.cfg
            _, depth = session.views.render_camera(look_matrix(*w.camera), c.width, c.height, c.hfov, depth=True)
            obs["depth"] = np.minimum(depth, c.depth_max).astype(np.float32)[..., None]
        obs["bump"] = np.array([1.0 if w.bumped else 0.0], np.float32)
        obs["pose"] = odometry(self.start, w.pose)
        return obs

    # --- what a task adds -----------------------------------------------------------------------------------------
    def setup(self, session) -> None:
        """Before the first frame: place the robot, choose what the user asks for."""

    def after_act(self, session, f: FrameInput, action: np.ndarray) -> None:
        """After the agent acted (interactions)."""

    def advance(self, session, f: FrameInput) -> None:
        """Every frame, after the robot moved (bookkeeping of the metrics)."""

    def info(self, session) -> dict:
        return {}

    def privileged(self, session) -> dict:
        return {"world": session.world}

    def semantic_map(self, session):
        raise ConfigError(f"{self.spec.cli} gives agents no semantic map")

    def report(self, session, estimates: dict) -> None:
        raise ConfigError(f"{self.spec.cli} scores no estimates")


# --- speaker following ---------------------------------------------------------------------------------------------
class _UserPerson:
    """The user as the following oracle's ``person`` (its position; the user decides where they go)."""

    finished = False
    escorting = False

    def __init__(self):
        self.pos = np.zeros(2)

    def upcoming(self, metres: float) -> np.ndarray:
        return self.pos[None].copy()


class FollowMe(RobotInTheLoop):
    """Speaker following with the user as the person. Metrics as the env's (``time_in_band``: steps at 1.0-2.5 m
    geodesic; ``mean_distance_m``; ``lost_s`` beyond 5 m; ``collisions``; ``time_s``); ``catch_success``: at the
    end the robot is within 1 m (geodesic) of the user and has moved less than 5 cm in its last second. Headless:
    the user walks to a place in another room at 0.6 m/s (a guide's pace for a TurtleBot), talking in 2-4 s spells
    with 2-3 s pauses (espeak-ng), then stands."""

    spec_name = "SpeakerFollowing"
    VOICE = "follow me please. this way. i am over here. come along"

    def setup(self, session) -> None:
        from sonicverse_core.tasks.base import SemanticMap

        self.map = SemanticMap.of(session.world, tuple(session.world.pose))
        self.person = _UserPerson()
        self.dist: list[float] = []
        self.recent: list[np.ndarray] = []
        if session.audio is not None and not session.audio.live:
            _speak_with_pauses(session, self.VOICE, gap_s=2.5)

    def headless_input(self, session, rate: float):
        from app.vr.headless import WalkTrajectory

        others = [r for r in session.scene.rooms if r.type != "living room"]
        goal = session.grid.sample(self.rng, 1, room=others[int(self.rng.integers(len(others)))].name)[0] \
            if others else session.grid.sample(self.rng, 1)[0]
        return WalkTrajectory(session.scene, session.grid, session.spawn, goal, rate, reach=0.0, speed=0.6)

    def after_act(self, session, f, action) -> None:
        g = session.world.grid
        d = g.geodesic_distance(session.world.pose[:2], self.user)
        self.dist.append(d if math.isfinite(d) else float(np.hypot(*(session.world.pose[:2] - self.user))))
        self.recent = (self.recent + [session.world.pose[:2].copy()])[-int(1.0 / STEP) - 1:]

    def advance(self, session, f) -> None:
        self.person.pos = self.user.copy()

    def semantic_map(self, session):
        return self.map

    def privileged(self, session) -> dict:
        d = self.dist[-1] if self.dist else float(np.hypot(*(session.world.pose[:2] - self.person.pos)))
        return {"world": session.world, "person": self.person, "distance": d}

    def summary(self) -> dict:
        d = np.array(self.dist) if self.dist else np.zeros(0)
        moved = float(np.hypot(*(self.recent[-1] - self.recent[0]))) if len(self.recent) > 1 else 0.0
        return {"agent": self.agent_name, "steps": self.steps,
                "time_in_band": float(np.mean((d >= 1.0) & (d <= 2.5))) if len(d) else None,
                "mean_distance_m": float(d.mean()) if len(d) else None,
                "lost_s": float(np.sum(d > 5.0) * STEP), "collisions": self.collisions,
                "catch_success": float(len(d) > 0 and d[-1] <= 1.0 and moved < 0.05),
                "time_s": self.steps * STEP}


# --- voice retrieval -----------------------------------------------------------------------------------------------
class FetchForMe(RobotInTheLoop):
    """Voice retrieval with the user as the person: the user asks for an object the robot can carry; the robot
    starts 3-10 m away (geodesic) and must put one of that category down within 1 m of the user. Offline audio:
    the command (espeak-ng, a category drawn from the seed among the scene's carriable ones) is said every 8 s until
    the robot picks something up, then "over here" every 3 s; with live audio the user says it (``category`` in
    the summary is then what the agent understood). Metrics: ``sr``, ``command_accuracy`` (the first object picked
    up is of the asked category), ``speaker_azimuth_error_deg`` and ``speaker_distance_error_m`` (the agent's first
    report, as in the env, with ``same_room``), ``time_s``, ``collisions``, ``path_length_m``."""

    spec_name = "VoiceRetrieval"
    n_actions = 3

    def setup(self, session) -> None:
        from sonicverse_core.tasks.base import SemanticMap
        from sonicverse_core.tasks.retrieval import SPOKEN, TEMPLATES

        w = session.world
        cats = sorted({o.category for o in w.scene.objects if o.movable and o.category in SPOKEN})
        if not cats:
            raise ConfigError(f"{session.cfg.scene} holds nothing the robot can carry")
        self.category = cats[int(self.rng.integers(len(cats)))]
        self.text = TEMPLATES[int(self.rng.integers(len(TEMPLATES)))].format(SPOKEN[self.category])
        self.targets = [o.name for o in w.scene.objects if o.movable and o.category == self.category]
        f = w.grid.distance_field(session.spawn)
        cand = w.grid.sample(self.rng, 64)
        geo = w.grid.geodesic_from_field(f, cand)
        ok = np.flatnonzero((geo >= 3.0) & (geo <= 10.0))
        if len(ok):
            s = cand[int(ok[0])]
            w.place_robot(float(s[0]), float(s[1]), float(self.rng.uniform(-180, 180)))
        self.map = SemanticMap.of(w, tuple(w.pose))
        self.first_pick = self.placed = None
        self.understood = False
        self.success = False
        self.estimate = None
        self.calling = False
        self.live = session.audio is not None and session.audio.live
        if session.audio is not None and not self.live:
            _speak_with_pauses(session, self.text, gap_s=8.0)

    def headless_input(self, session, rate: float):
        from app.vr.headless import EYE_HEIGHT, hand_poses
        from app.vr.transforms import look_matrix

        p = session.spawn.copy()
        z = session.scene.floor_z + EYE_HEIGHT
        yaw0 = float(self.rng.uniform(0, 360))

        def stand(k, t):  # stands and looks around a little
            head = look_matrix(p[0], p[1], z, yaw0 + 30.0 * math.sin(0.4 * t), -5.0)
            return head, hand_poses(head), np.ones(2, bool), np.zeros(2, np.uint64)
        return stand

    def info(self, session) -> dict:
        return {"carrying": session.world.carried}

    def privileged(self, session) -> dict:
        return {"world": session.world, "person": self.user.copy(), "category": self.category, "text": self.text,
                "targets": list(self.targets)}

    def semantic_map(self, session):
        return self.map

    def report(self, session, estimates: dict) -> None:
        xy = np.asarray(estimates.get("speaker"), float)
        if set(estimates) != {"speaker"} or xy.shape != (2,) or not np.all(np.isfinite(xy)):
            raise ConfigError("report(speaker=(x, y)) with a finite position")
        if self.estimate is None:
            w = session.world
            ra, rb = w.scene.room_at(w.pose[:2]), w.scene.room_at(self.user)
            self.estimate = (xy, w.pose[:2].copy(), self.user.copy(), ra is not None and ra is rb)

    def after_act(self, session, f, a) -> None:
        from sonicverse_core.errors import ActionError
        from sonicverse_core.tasks.retrieval import VoiceRetrieval

        if a.shape[0] < 3 or a[2] <= 0:
            return
        w = session.world
        try:
            if w.carried is None:
                name = VoiceRetrieval._in_front(w)
                if name is None:
                    return
                w.pick(name)
                if self.first_pick is None:
                    self.first_pick = name
                    self.understood = name in self.targets
                if not self.live and not self.calling and session.audio is not None:
                    self.calling = True
                    _speak_with_pauses(session, "over here. i am over here", gap_s=3.0)
                return
            name = w.place()
        except ActionError:
            return
        self.placed = name
        d = float(np.hypot(*(w.scene.object(name).position[:2] - self.user)))
        self.success = name in self.targets and d <= 1.0
        self.done = True

    def summary(self) -> dict:
        az = dist = same = None
        if self.estimate is not None:
            est, robot, user, same = self.estimate
            a, b = est - robot, user - robot
            az = abs((math.degrees(math.atan2(a[1], a[0]) - math.atan2(b[1], b[0])) + 180.0) % 360.0 - 180.0)
            dist = abs(float(np.hypot(*a) - np.hypot(*b)))
        return {"agent": self.agent_name, "category": self.category, "text": None if self.live else self.text,
                "sr": float(self.success), "command_accuracy": float(self.understood), "first_pick": self.first_pick,
                "placed": self.placed, "speaker_azimuth_error_deg": az, "speaker_distance_error_m": dist,
                "same_room": same,
                "time_s": self.steps * STEP, "collisions": self.collisions, "path_length_m": self.path_length}


def _speak_with_pauses(session, text: str, gap_s: float) -> None:
    """The offline voice (what the user says at the avatar's mouth, looping): 0.5 s of quiet (as in the env: a
    listener learns the room's noise floor first), ``text``, then ``gap_s`` of quiet."""
    from assets_manifest.speech import speak

    sr = session.cfg.sample_rate
    x = speak(text, sample_rate=sr)[0]
    session.audio.voice = np.r_[np.zeros(sr // 2, np.float32), x, np.zeros(int(gap_s * sr), np.float32)
                                ].astype(np.float32)
    session.audio.voice_at = 0


# --- orientation training ------------------------------------------------------------------------------------------
class OrientationTrials(FrameTask):
    """Auditory orientation training in the VR loop (audio only; no robot is needed). Each trial: a stimulus (three
    50 ms noise bursts every 0.4 s, looping) plays from a place 1.5-3 m from the user's head, anywhere around them
    at -20..+40 degrees elevation; the user turns to face it (``mode`` 'turn') or walks to it ('walk') and pulls
    the right trigger; then the next trial. Turn trials score the azimuth error after mirroring a front-back
    reversal back, the elevation error and the response time; walk trials success within 0.5 m, path efficiency,
    time to target. The summary has the registry's metric keys (means over the trials) and every trial.

    Headless: the simulated participant (:class:`sonicverse_core.tasks.orientation.SimulatedListener`) turns its
    head to what it perceives over its response time, or walks there, and pulls the trigger."""

    name = "orientation-training"

    def __init__(self, trials: int = 10, mode: str = "turn", seed: int = 0, participant: dict | None = None):
        from sonicverse_core.tasks.orientation import SimulatedListener

        if mode not in ("turn", "walk"):
            raise ConfigError(f"mode must be 'turn' or 'walk', got '{mode}'")
        if trials < 1:
            raise ConfigError("trials must be >= 1")
        self.n, self.mode = int(trials), mode
        self.rng = np.random.default_rng(seed)
        self.listener = SimulatedListener(**(participant or {}))
        self.rows: list[dict] = []
        self.done = False
        self._trigger = False

    def audio_sources(self, scene):
        from app.audio_rt.config import SourceSpec

        sr = 48_000
        n = int(0.4 * sr)
        one = np.zeros(n, np.float32)
        burst = np.random.default_rng(7).standard_normal(int(0.05 * sr)).astype(np.float32) * 0.3
        burst *= np.hanning(len(burst)).astype(np.float32)
        one[:len(burst)] = burst
        return [(None, SourceSpec(sound=np.tile(one, 3), position=(0.0, 0.0, -50.0), sample_rate=sr))]

    def reset(self, session) -> None:
        self.session = session
        self.k = -1
        self._next(session, None)

    def _next(self, session, f) -> None:
        self.k += 1
        if self.k >= self.n:
            self.done = True
            if session.audio is not None:
                session.audio.move_source(0, (0.0, 0.0, -50.0))  # far below the floor: silent enough
            return
        head = session.spawn if f is None else _user_xy(f)
        hz = session.scene.floor_z + 1.6 if f is None else float(f.head[2, 3])
        yaw = 0.0 if f is None else _yaw(f.head)
        for _ in range(100):
            az, el = float(self.rng.uniform(-180, 180)), float(self.rng.uniform(-20, 40))
            r = float(self.rng.uniform(1.5, 3.0))
            a = math.radians(yaw + az)
            h = r * math.cos(math.radians(el))
            pos = np.array([head[0] + h * math.cos(a), head[1] + h * math.sin(a), hz + r * math.sin(math.radians(el))])
            if self.mode == "turn" or session.grid.is_navigable(pos[None, :2])[0]:
                break
        self.trial = {"trial": self.k, "mode": self.mode, "az": az, "el": el, "pos": pos, "t0": None,
                      "start": head.copy(), "walked": 0.0, "last": head.copy(), "yaw0": yaw}
        if session.audio is not None:
            session.audio.move_source(0, tuple(pos))

    def step(self, session, f: FrameInput) -> None:
        if self.done:
            return
        tr = self.trial
        if tr["t0"] is None:
            tr["t0"] = f.t
        p = _user_xy(f)
        tr["walked"] += float(np.hypot(*(p - tr["last"])))
        tr["last"] = p
        down = f.pressed(RIGHT, BUTTON_TRIGGER)
        if down and not self._trigger:
            self._score(session, f)
            self._next(session, f)
        self._trigger = down

    def _score(self, session, f) -> None:
        from sonicverse_core.tasks.orientation import mirror, wrap

        tr = self.trial
        p = _user_xy(f)
        v = tr["pos"][:2] - p
        row = {"trial": tr["trial"], "mode": tr["mode"], "response_time_s": f.t - tr["t0"]}
        if tr["mode"] == "turn":
            # relative to the head at the trial's start: where the sound was, where the user turned to
            w0 = tr["start"]
            u = tr["pos"][:2] - w0
            rel = float(wrap(math.degrees(math.atan2(u[1], u[0])) - tr["yaw0"]))
            resp = float(wrap(_yaw(f.head) - tr["yaw0"]))
            reversal = abs(abs(rel) - 90.0) > 15.0 and math.cos(math.radians(rel)) * math.cos(math.radians(resp)) < 0
            err = float(wrap(resp - (float(mirror(rel)) if reversal else rel)))  # a reversal mirrored back
            el_true = math.degrees(math.atan2(tr["pos"][2] - f.head[2, 3], float(np.hypot(*u))))
            row.update(azimuth_error_deg=abs(err), elevation_error_deg=abs(_pitch(f.head) - el_true),
                       front_back_confusion=float(reversal), target_az=rel, response_az=resp)
        else:
            d = float(np.hypot(*v))
            straight = float(np.hypot(*(tr["pos"][:2] - tr["start"])))
            row.update(walk_success=float(d <= 0.5), path_efficiency=min(1.0, straight / max(tr["walked"], 1e-6)),
                       time_to_target_s=f.t - tr["t0"], distance_m=d)
        self.rows.append(row)

    def headless_input(self, session, rate: float):
        """The simulated participant: per trial, a perceived direction (the listener model's noise and reversals),
        a turn of the head to it over the response time (or a walk there at the model's speed), the trigger."""
        from app.vr.headless import EYE_HEIGHT, hand_poses
        from app.vr.transforms import look_matrix

        z = session.scene.floor_z + EYE_HEIGHT
        state = {"k": -1, "from": None, "to": None, "t0": 0.0, "rt": 1.0, "press": None,
                 "pos": session.spawn.copy(), "yaw": 0.0, "pitch": 0.0}
        rng = np.random.default_rng(self.rng.integers(2 ** 32))

        def traj(k, t):
            s = state
            if self.done:
                head = look_matrix(s["pos"][0], s["pos"][1], z, s["yaw"], s["pitch"])
                return head, hand_poses(head), np.ones(2, bool), np.zeros(2, np.uint64)
            tr = getattr(self, "trial", None)
            if tr is not None and s["k"] != tr["trial"]:  # a new trial: perceive it, plan the response
                s["k"] = tr["trial"]
                v = tr["pos"][:2] - s["pos"]
                rel = (math.degrees(math.atan2(v[1], v[0])) - s["yaw"] + 180.0) % 360.0 - 180.0
                el = math.degrees(math.atan2(tr["pos"][2] - z, float(np.hypot(*v))))
                ra, re, rt = self.listener.turn(rel, el, tr["trial"], "none", 0.0, rng)
                s["from"] = (s["pos"].copy(), s["yaw"], s["pitch"])
                if self.mode == "turn":
                    s["to"] = (s["pos"].copy(), s["yaw"] + ra, re)
                else:
                    d = float(np.hypot(*v))
                    a = math.radians(s["yaw"] + ra)
                    s["to"] = (s["pos"] + d * np.array([math.cos(a), math.sin(a)]), s["yaw"] + ra, 0.0)
                    rt = rt + d / self.listener.walk_speed
                s["t0"], s["rt"], s["press"] = t, rt, None
            if s["to"] is not None:
                a = min(1.0, (t - s["t0"]) / max(s["rt"], 1e-3))
                (p0, y0, e0), (p1, y1, e1) = s["from"], s["to"]
                s["pos"], s["yaw"], s["pitch"] = p0 + a * (p1 - p0), y0 + a * (y1 - y0), e0 + a * (e1 - e0)
                if a >= 1.0 and s["press"] is None:
                    s["press"] = k
            head = look_matrix(s["pos"][0], s["pos"][1], z, s["yaw"], s["pitch"])
            b = np.zeros(2, np.uint64)
            if s["press"] is not None and k - s["press"] < 2:
                b[RIGHT] = BUTTON_TRIGGER
            return head, hand_poses(head), np.ones(2, bool), b
        return traj

    def summary(self) -> dict:
        turn = [r for r in self.rows if r["mode"] == "turn"]
        walk = [r for r in self.rows if r["mode"] == "walk"]
        mean = lambda rows, k: float(np.mean([r[k] for r in rows])) if rows else None  # noqa: E731
        return {"trials": len(self.rows), "mode": self.mode,
                "azimuth_error_deg": mean(turn, "azimuth_error_deg"),
                "elevation_error_deg": mean(turn, "elevation_error_deg"),
                "front_back_confusion_rate": mean(turn, "front_back_confusion"),
                "response_time_s": mean(self.rows, "response_time_s"),
                "walk_success": mean(walk, "walk_success"), "path_efficiency": mean(walk, "path_efficiency"),
                "time_to_target_s": mean(walk, "time_to_target_s"), "rows": self.rows}


def _yaw(head: np.ndarray) -> float:
    from app.vr.transforms import head_pose

    return float(head_pose(head)[3])


def _pitch(head: np.ndarray) -> float:
    from app.vr.transforms import head_pose

    return float(head_pose(head)[4])



def make_frame_task(task: str, agent: str | None = None, seed: int = 0, trials: int = 10, mode: str = "turn",
                    checkpoint=None):
    """The VR frame task of a registry task (by any of its names) with its agent (and a learned agent's
    ``checkpoint``) or participant settings."""
    from sonicverse_core.tasks.registry import load, task_spec

    spec = task_spec(task)
    if spec.frame_task is None:
        raise ConfigError(f"task '{spec.cli}' has no VR version; use one of "
                          f"{', '.join(s.cli for s in _with_frame_task())}")
    cls = load(spec.frame_task)
    if issubclass(cls, RobotInTheLoop):
        return cls(agent=agent, seed=seed, checkpoint=checkpoint)
    if agent not in (None, "simulated"):
        raise ConfigError(f"{spec.cli} in VR is done by the user (the headless backend simulates one); "
                          f"--agent takes 'simulated' only")
    return cls(trials=trials, mode=mode, seed=seed)


def _with_frame_task():
    from sonicverse_core.tasks.registry import TASKS

    return [s for s in TASKS.values() if s.frame_task]
