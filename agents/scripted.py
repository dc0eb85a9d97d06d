"""Scripted baselines for the navigation tasks.

Every agent has ``reset(env, obs, info)`` and ``act(obs, info) -> action``. ``env`` is the unwrapped environment:
agents read its action space, robot and step length; only privileged agents read state beyond the observations,
and they do it through the one documented channel, ``env.privileged()``. Randomness comes from the Generator
passed in.

* ``random``: uniform continuous wheel velocities; like the paper's baseline it stops automatically at the goal
  (privileged: it reads ``env.privileged()["at_goal"]``; the AudioGoal tasks end there by themselves).
* ``oracle`` (privileged: ``world``, ``goals``): drives the geodesic shortest path (string-pulled) with a pursuit
  controller; proves the metrics (SR and SPL near 1).
* ``gan-itd``: estimates the sound's direction from the interaural time difference (spinning in place to resolve
  front from back), triangulates the source from bearings taken at different places, builds an occupancy map from
  depth, and plans on it (Dijkstra over the map) to the estimate. (``gan`` itself, Gan et al.'s design, is
  :mod:`agents.gan`; the learned-localiser version before it is :class:`GanLocalizerAgent`.)
"""
from __future__ import annotations

import math

import numpy as np


def _wheels(v: float, w: float, robot) -> np.ndarray:
    """Normalised wheel velocities for a body velocity v (m/s) and turn rate w (rad/s)."""
    vl = v - w * robot.wheel_base / 2
    vr = v + w * robot.wheel_base / 2
    a = np.array([vl, vr]) / robot.max_speed
    m = np.max(np.abs(a))
    return a / m if m > 1 else a


def _pursue(pose_xy, yaw_deg, target, robot, dt, slow_within: float = 0.0) -> np.ndarray:
    d = np.asarray(target, float) - np.asarray(pose_xy, float)
    dist = float(np.hypot(*d))
    err = (math.degrees(math.atan2(d[1], d[0])) - yaw_deg + 180.0) % 360.0 - 180.0
    wmax = math.radians(robot.max_turn_deg)
    w = max(-wmax, min(wmax, math.radians(err) / dt * 0.9))
    if abs(err) > 35.0:
        return _wheels(0.0, w, robot)
    v = robot.max_speed * max(0.0, math.cos(math.radians(err)))
    if slow_within > 0:
        v = min(v, max(dist, 0.05) / dt)
    return _wheels(v, w, robot)


def turn_steps(robot, dt: float) -> int:
    """Steps of turning on the spot at the robot's top rate that make a full turn (and one more)."""
    return int(math.ceil(360.0 / (robot.max_turn_deg * dt))) + 1


def turn_toward(p, yaw_deg: float, xy, robot, dt: float, offset: float = 0.0,
                tol: float = 8.0) -> tuple[np.ndarray, bool]:
    """Wheel commands turning a robot at ``p`` facing ``yaw_deg`` on the spot toward ``xy`` (plus ``offset``
    degrees), and whether it already faces it within ``tol`` degrees (then the wheels are still)."""
    v = np.asarray(xy, float) - np.asarray(p, float)
    err = (math.degrees(math.atan2(v[1], v[0])) + offset - yaw_deg + 180.0) % 360.0 - 180.0
    if abs(err) < tol:
        return np.zeros(2), True
    rate = math.copysign(min(abs(math.radians(err)) / dt * 0.8, math.radians(robot.max_turn_deg)), err)
    return _wheels(0.0, rate, robot), False


def next_waypoint(grid, path: np.ndarray, k: int, p: np.ndarray) -> int:
    """The waypoint of ``path`` to steer for from ``p``, at or after ``k``: past those within 0.2 m whose next one is
    in line of sight, and always past one within 5 cm (it gives no heading: steering for it, a robot spins on the
    spot)."""
    while k < len(path) - 1:
        d = float(np.hypot(*(path[k] - p)))
        if d < 0.05 or (d < 0.2 and grid.line_of_sight(p, path[k + 1])):
            k += 1
        else:
            break
    return k


class Agent:
    name = "agent"
    stop_dim = False

    def __init__(self, rng: np.random.Generator | None = None):
        self.rng = rng if rng is not None else np.random.default_rng(0)

    def reset(self, env, obs, info) -> None:
        self.env = env
        self.stop_dim = env.action_space.shape[0] == 3
        self.robot = env.robot
        self.dt = env.cfg.step_seconds

    def _out(self, wheels, stop: bool = False) -> np.ndarray:
        wheels = np.clip(np.asarray(wheels, float), -1, 1)
        if self.stop_dim:
            return np.array([wheels[0], wheels[1], 1.0 if stop else -1.0], np.float32)
        return wheels.astype(np.float32)

    def act(self, obs, info) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError


class RandomAgent(Agent):
    """Uniform wheel commands from its Generator; it reads none of its observations, so the env it runs in renders
    no camera and computes no spectrogram for it (:meth:`env_kwargs`; the episodes and scores are the same, tested)."""

    name = "random"

    def env_kwargs(self) -> dict:
        return {"sensors": ("pose",)}

    def act(self, obs, info):
        if self.stop_dim and self.env.privileged().get("at_goal"):  # the paper's random baseline stops at the goal
            return self._out([0.0, 0.0], stop=True)
        return self._out(self.rng.uniform(-1.0, 1.0, 2))


class OracleAgent(Agent):
    """Privileged: reads the world, the goals and whether it is at one (``env.privileged()``)."""

    name = "oracle"

    def reset(self, env, obs, info):
        super().reset(env, obs, info)
        self._plan()

    def _plan(self):
        priv = self.env.privileged()
        w, goals = priv["world"], priv["goals"]
        from_robot = w.grid.distance_field(w.pose[:2])
        g = goals[int(np.argmin(w.grid.geodesic_from_field(from_robot, goals)))]
        path, length = w.grid.shortest_path(w.pose[:2], g)
        self.path = path if np.isfinite(length) else np.array([w.pose[:2], g])
        self.k = 1

    def act(self, obs, info):
        priv = self.env.privileged()
        w = priv["world"]
        if priv["at_goal"]:
            return self._out([0.0, 0.0], stop=True)
        p = w.pose[:2]
        while self.k < len(self.path) - 1 and np.linalg.norm(self.path[self.k] - p) < 0.15:
            self.k += 1
        if w.bumped:
            self._plan()
        return self._out(_pursue(p, w.pose[2], self.path[min(self.k, len(self.path) - 1)], self.robot, self.dt,
                                 slow_within=0.3 if self.k >= len(self.path) - 1 else 0.0))


class MapDriver(Agent):
    """What agents that know the map share: drive a world's (or a map's) grid to a goal along its shortest path,
    re-planned when the goal changes or the robot bumps, and turn to face a place. ``w`` is anything with ``pose``
    (x, y, yaw degrees), ``grid`` (a NavGrid) and ``bumped``: the world for oracles, the robot's map and odometry for
    the scripted agents."""

    def reset(self, env, obs, info) -> None:
        super().reset(env, obs, info)
        self.path, self.k, self.goal = None, 1, None

    def _follow(self, w, goal, slow: float = 0.0) -> np.ndarray:
        p = w.pose[:2]
        if self.path is None or self.goal is None or np.any(self.goal != goal) or w.bumped:
            path, length = w.grid.shortest_path(p, goal)
            self.path = path if np.isfinite(length) and len(path) > 1 else np.array([p, goal])
            self.k, self.goal = 1, np.array(goal, float)
        while (self.k < len(self.path) - 1 and np.linalg.norm(self.path[self.k] - p) < 0.2
               and w.grid.line_of_sight(p, self.path[self.k + 1])):
            self.k += 1
        return _pursue(p, w.pose[2], self.path[min(self.k, len(self.path) - 1)], self.robot, self.dt,
                       slow_within=slow)

    def _face(self, w, xy, offset: float = 0.0) -> tuple[np.ndarray, bool]:
        return turn_toward(w.pose[:2], w.pose[2], xy, self.robot, self.dt, offset)


class MapAgent(Agent):
    """What the sensor-only agents share: the odometry pose from the ``pose`` observation, an occupancy grid of
    ``SIZE`` x ``SIZE`` cells of ``CELL`` m around the start (filled from depth), and a planner on it."""

    CELL = 0.1
    SIZE = 240  # cells: 24 m x 24 m around the start

    def reset(self, env, obs, info):
        super().reset(env, obs, info)
        self.occ = np.zeros((self.SIZE, self.SIZE), np.int16)
        self._fx = (env.cfg.width / 2) / math.tan(math.radians(env.cfg.hfov) / 2)

    def _map_depth(self, obs, p, yaw):
        if "depth" in obs:
            map_depth(self.occ, obs["depth"][..., 0], p, yaw, self._fx, self.robot.camera_height, self.CELL)

    def _pose(self, obs):
        x, y, s, c = (float(v) for v in obs["pose"])
        return np.array([x, y]), math.degrees(math.atan2(s, c))

    def _cell(self, xy):
        return np.floor(np.asarray(xy) / self.CELL).astype(int) + self.SIZE // 2

    def _reachable(self, p, inflate: int = 2):
        """Where the robot at ``p`` can drive on the map: (its cell, the blocked grid, path lengths in cells from it,
        predecessors; :func:`grid_field`), obstacles dilated by ``inflate`` cells, or fewer when that leaves under 50
        cells reachable (in a narrow doorway the dilated map may shut the robot in)."""
        from scipy.ndimage import binary_dilation

        s = np.clip(self._cell(p), 0, self.SIZE - 1)
        for k in range(inflate, -1, -1):
            blocked = binary_dilation(self.occ >= 2, iterations=k) if k else self.occ >= 2
            blocked[s[0], s[1]] = False
            dist, pred = grid_field(blocked, s)
            dist = dist.reshape(self.SIZE, self.SIZE)
            if np.count_nonzero(np.isfinite(dist)) >= 50:
                break
        return s, blocked, dist, pred

    def _plan_to(self, p, goal) -> None:
        """``self.path``: waypoints from ``p`` to ``goal`` round what the map holds as blocked (dilated 2 cells;
        unknown space counts as free); the goal alone when there is no way."""
        from scipy.ndimage import binary_dilation

        blocked = binary_dilation(self.occ >= 2, iterations=2)
        s, g = self._cell(p), np.clip(self._cell(goal), 0, self.SIZE - 1)
        blocked[s[0], s[1]] = False
        blocked[g[0], g[1]] = False
        path = _grid_path(blocked, tuple(s), tuple(g))
        self.path = np.array([goal]) if path is None else (np.array(path, float) - self.SIZE // 2 + 0.5) * self.CELL
        self.k = min(2, len(self.path) - 1)


class GanItdAgent(MapAgent):
    """Hand-made binaural localisation (interaural delays voted over spins in place, bearings triangulated) + depth
    occupancy map + planner; uses observations only (audio, depth, pose). Kept for comparison as ``gan-itd``: the
    ``gan`` baseline (:class:`agents.gan.GanAgent`) localises by the level and the level difference between the
    ears."""

    name = "gan-itd"
    ITD_MAX = 0.00066  # s: the KEMAR head's largest interaural delay

    def reset(self, env, obs, info):
        super().reset(env, obs, info)
        self.sr = env.cfg.sample_rate
        self.bearings: list[tuple[np.ndarray, float, float]] = []  # (position, world bearing rad, weight)
        self.goal = None
        self.votes = np.zeros(72)
        self._listen()
        self.since_listen = 0
        self.relistens = 0
        self.quiet = 0
        self.path = None
        self.k = 0

    def _listen(self) -> None:
        """Start a full turn in place, voting for the sound's bearing."""
        self.spin_left = turn_steps(self.robot, self.dt)
        self.votes[:] = 0

    # --- perception -------------------------------------------------------------------------------------------
    def _itd(self, audio: np.ndarray) -> tuple[float, float]:
        """(interaural delay s, left leads > 0; energy)."""
        return itd_gcc_phat(audio, self.sr, self.ITD_MAX)

    # --- estimation and planning ------------------------------------------------------------------------------
    def _estimate(self):
        if not self.bearings:
            return None
        P = np.array([b[0] for b in self.bearings])
        th = np.array([b[1] for b in self.bearings])
        wgt = np.array([b[2] for b in self.bearings])
        dirs = np.stack([np.cos(th), np.sin(th)], 1)
        if len(P) >= 2 and np.ptp(P, axis=0).max() > 0.5:
            A = np.zeros((2, 2))
            bvec = np.zeros(2)
            for p, dvec, w in zip(P, dirs, wgt):
                M = np.eye(2) - np.outer(dvec, dvec)
                A += w * M
                bvec += w * M @ p
            if np.linalg.cond(A) < 1e3:
                g = np.linalg.solve(A, bvec)
                last = P[-1]
                if np.dot(g - last, dirs[-1]) > 0 and np.linalg.norm(g - last) < 12:
                    return g
        return P[-1] + 2.5 * dirs[-1]

    def _plan(self, p):
        self._plan_to(p, self.goal)

    def act(self, obs, info):
        p, yaw = self._pose(obs)
        self._map_depth(obs, p, yaw)
        itd, energy = self._itd(obs["audio"]) if "audio" in obs else (0.0, 0.0)
        audible = energy > 1e-9
        self.quiet = 0 if audible else self.quiet + 1
        if self.spin_left > 0:
            if audible:
                lat = math.asin(max(-1.0, min(1.0, itd / self.ITD_MAX)))
                for cand in (math.radians(yaw) + lat, math.radians(yaw) + math.pi - lat):
                    b = int(round(math.degrees(cand) / 5.0)) % 72
                    self.votes[b] += math.sqrt(energy)
                    self.votes[(b + 1) % 72] += 0.5 * math.sqrt(energy)
                    self.votes[(b - 1) % 72] += 0.5 * math.sqrt(energy)
            self.spin_left -= 1
            if self.spin_left == 0 and self.votes.max() > 0:
                self.bearings.append((p.copy(), math.radians(5.0 * int(np.argmax(self.votes))),
                                      float(self.votes.max())))
                self.goal = self._estimate()
                self._plan(p)
                self.since_listen = 0
            return self._out(_wheels(0.0, math.radians(self.robot.max_turn_deg), self.robot))
        if self.goal is None:
            self.goal = p + 2.0 * np.array([math.cos(math.radians(yaw)), math.sin(math.radians(yaw))])
            self._plan(p)
        self.since_listen += 1
        if self.since_listen >= 25 and self.quiet < 5:  # listen again from here
            self._listen()
            return self._out([0.0, 0.0])
        if self.since_listen % 8 == 0 or (obs.get("bump") is not None and obs["bump"][0] > 0):
            self._plan(p)
        if np.linalg.norm(self.goal - p) < 0.3:
            if self.quiet < 5 and self.relistens < 4:  # still audible: listen again here before stopping
                self.relistens += 1
                self._listen()
                self.bearings = self.bearings[-1:]
                return self._out([0.0, 0.0])
            return self._out([0.0, 0.0], stop=True)
        while self.k < len(self.path) - 1 and np.linalg.norm(self.path[self.k] - p) < 0.2:
            self.k += 1
        return self._out(_pursue(p, yaw, self.path[self.k], self.robot, self.dt))


class GanLocalizerAgent(MapAgent):
    """The ``gan`` baseline of sessions 14-51, kept for comparison (``--agent agents.scripted:GanLocalizerAgent``): a
    learned sound localiser (:mod:`agents.localizer`) + an occupancy map from depth + a planner; reads observations
    only (audio, spectrogram, depth, pose, bump). 1.0% SR on SemanticAudioNav and 20.0% on AudioGoal (200 test
    episodes each, README); :mod:`agents.gan` replaced it.

    It turns once on the spot (hearing the sound from every heading), then drives to its estimate of the sound's
    position. Each audible step's prediction votes into a grid over the odometry frame (a Gaussian around the
    predicted point, wider the farther it is, weighted by the prediction's confidence; older votes fade by ``FADE``
    a step); the estimate is the grid's peak. (Votes from a localiser whose errors were front-back confusions would
    spread over mirror images that move as the robot turns while the true position stays put. The shipped localiser
    is at chance on steady sounds in these homes, its model card says why, so here the grid mostly averages noise.)
    When the sound stops the robot keeps its last estimate. It has arrived within ``STOP_RADIUS`` of the estimate, or
    within ``NEAR`` of it when it lies in mapped obstacle or the robot has come no nearer to it for ``STUCK`` steps.
    Arrived, it circles the estimate (hearing it from new places) while the sound plays, and stops (tasks with a stop
    action) once the sound has stopped or the localiser hears the object within 0.7 ``NEAR``; on AudioGoal (no stop)
    it circles until the task ends the episode."""

    name = "gan-localizer"
    VOTE_CELL = 0.2  # m
    FADE = 0.98
    STOP_RADIUS = 0.5
    NEAR = 1.0
    STUCK = 30

    def __init__(self, rng: np.random.Generator | None = None, checkpoint=None):
        super().__init__(rng)
        from agents.learned import CHECKPOINTS
        from agents.localizer import load

        self.localizer, _ = load(checkpoint or CHECKPOINTS / "sound-localizer.pt")

    def reset(self, env, obs, info):
        super().reset(env, obs, info)
        self.sr = env.cfg.sample_rate
        n = int(round(self.SIZE * self.CELL / self.VOTE_CELL))
        self.votes = np.zeros((n, n))
        c = (np.arange(n) - n / 2 + 0.5) * self.VOTE_CELL
        self._vx, self._vy = np.meshgrid(c, c, indexing="ij")
        self.heard, self.quiet, self.near_now = 0, 0, False
        self.goal = None
        self.closest, self.closest_to, self.no_closer = math.inf, np.zeros(2), 0
        self.spin_left = turn_steps(self.robot, self.dt)
        self.path, self.k, self.since_plan, self.circle = None, 0, 0, 0

    def _hear(self, obs, p, yaw) -> None:
        from agents.localizer import audible

        self.votes *= self.FADE
        self.near_now = False
        if "spectrogram" not in obs or not audible(obs["audio"]):
            self.quiet += 1
            return
        self.quiet = 0
        c, s_, l1p = self.localizer.predict(obs["spectrogram"], obs["audio"], self.sr)
        conf = min(float(math.hypot(c, s_)), 1.0)
        b = math.radians(yaw) + math.atan2(s_, c)
        d = float(math.expm1(max(l1p, 0.0)))
        q = p + d * np.array([math.cos(b), math.sin(b)])
        sigma = 0.4 + 0.3 * d
        self.votes += conf ** 2 * np.exp(-((self._vx - q[0]) ** 2 + (self._vy - q[1]) ** 2) / (2 * sigma ** 2))
        self.heard += 1
        self.near_now = d < self.NEAR * 0.7 and conf > 0.7

    def _estimate(self):
        if self.heard == 0:
            return None
        i, j = np.unravel_index(int(np.argmax(self.votes)), self.votes.shape)
        return np.array([self._vx[i, j], self._vy[i, j]])

    def act(self, obs, info):
        p, yaw = self._pose(obs)
        self._map_depth(obs, p, yaw)
        self._hear(obs, p, yaw)
        turn = _wheels(0.0, math.radians(self.robot.max_turn_deg), self.robot)
        if self.spin_left > 0:
            self.spin_left -= 1
            return self._out(turn)
        est = self._estimate()
        if est is None:  # nothing heard yet: keep turning
            return self._out(turn)
        bumped = obs.get("bump") is not None and obs["bump"][0] > 0
        if self.circle and np.linalg.norm(est - self.circle_at) > self.NEAR:  # the estimate moved: go there
            self.circle = 0
        if self.circle == 0 and (self.goal is None or np.linalg.norm(est - self.goal) > 0.4 or bumped
                                 or self.since_plan >= 10):
            self.goal = est
            self._plan_to(p, est)
            self.since_plan = 0
        self.since_plan += 1
        dist = float(np.linalg.norm(est - p))
        if dist < self.closest - 0.1 or np.linalg.norm(est - self.closest_to) > 0.4:  # nearer, or a new estimate
            self.closest, self.closest_to, self.no_closer = dist, est, 0
        else:
            self.no_closer += 1
        c = self._cell(est)
        inside = bool(0 <= c[0] < self.SIZE and 0 <= c[1] < self.SIZE and self.occ[c[0], c[1]] >= 2)
        stuck = self.no_closer >= self.STUCK
        if dist < self.STOP_RADIUS or (dist < self.NEAR and (inside or stuck)) or self.circle:
            if self.stop_dim and (self.quiet >= 5 or self.near_now):
                return self._out([0.0, 0.0], stop=True)
            if self.circle == 0:
                self.circle_at = est
            if self.circle % 15 == 0 or bumped:  # circle the estimate
                a = math.radians(45.0 * (self.circle // 15))
                self.goal = est + 0.7 * np.array([math.cos(a), math.sin(a)])
                self._plan_to(p, self.goal)
            self.circle += 1
        while self.k < len(self.path) - 1 and np.linalg.norm(self.path[self.k] - p) < 0.2:
            self.k += 1
        return self._out(_pursue(p, yaw, self.path[self.k], self.robot, self.dt))


def gcc_phat(audio: np.ndarray, sr: int, max_itd: float) -> tuple[np.ndarray, float]:
    """(generalised cross-correlation with phase transform over lags -L..L, L = ceil(max_itd * sr) + 1; energy).
    A peak at lag k > 0 means the right ear hears the sound k samples after the left (the left ear leads)."""
    l, r = audio[0].astype(np.float64), audio[1].astype(np.float64)
    e = float(np.mean(l * l + r * r))
    lag = int(math.ceil(max_itd * sr)) + 1
    if e < 1e-12:
        return np.zeros(2 * lag + 1), 0.0
    n = len(l)
    X = np.fft.rfft(r, 2 * n) * np.conj(np.fft.rfft(l, 2 * n))
    cc = np.fft.irfft(X / (np.abs(X) + 1e-12), 2 * n)
    return np.concatenate([cc[-lag:], cc[: lag + 1]]), e


def onset_frames(audio: np.ndarray, tail: np.ndarray, frame: int = 320, hop: int = 160) -> tuple[np.ndarray, np.ndarray]:
    """(frames (2, k, frame), weights (k,)): frames of ``frame`` samples every ``hop`` over ``tail`` (the end of the
    previous block, at least ``frame`` samples) + ``audio``, each weighted by how much its energy rose over the two
    hops before it (log10 ratio above 0.3, i.e. +3 dB; 0 otherwise): the onsets, where the precedence effect takes
    the direction from the first wavefront."""
    y = np.concatenate([tail, audio], axis=1).astype(np.float64)
    starts = np.arange(tail.shape[1] - frame + hop, y.shape[1] - frame + 1, hop)
    if len(starts) == 0:
        return np.zeros((2, 0, frame)), np.zeros(0)
    fr = np.stack([y[:, s:s + frame] for s in starts], 1)
    e = (fr ** 2).mean(axis=(0, 2))
    before = np.array([(y[:, max(s - 2 * hop, 0):s] ** 2).mean() for s in starts]) + 1e-12
    return fr, np.maximum(0.0, np.log10(e / before + 1e-12) - 0.3) * (e > 1e-10)


def onset_gcc_phat(audio: np.ndarray, tail: np.ndarray, sr: int, max_itd: float, frame: int = 320,
                   hop: int = 160) -> tuple[np.ndarray, float]:
    """GCC-PHAT weighted towards onsets (the precedence effect: the first wavefront carries the direction, the
    room's reflections follow): each frame of :func:`onset_frames` weighted by its rise. Returns (weighted sum over
    lags -L..L, total weight)."""
    return frames_gcc_phat(*onset_frames(audio, tail, frame, hop), sr, max_itd)


def frames_gcc_phat(fr: np.ndarray, w: np.ndarray, sr: int, max_itd: float) -> tuple[np.ndarray, float]:
    """GCC-PHAT of frames (2, k, frame) weighted by ``w`` (k,) (:func:`onset_frames`): (weighted sum over lags
    -L..L, total weight)."""
    lag = int(math.ceil(max_itd * sr)) + 1
    if not np.any(w > 0):
        return np.zeros(2 * lag + 1), 0.0
    frame = fr.shape[2]
    X = np.fft.rfft(fr[1], 2 * frame) * np.conj(np.fft.rfft(fr[0], 2 * frame))
    cc = np.fft.irfft(X / (np.abs(X) + 1e-12), 2 * frame)
    cc = np.concatenate([cc[:, -lag:], cc[:, : lag + 1]], axis=1)
    return (w[:, None] * cc).sum(0), float(w.sum())


def itd_gcc_phat(audio: np.ndarray, sr: int, max_itd: float) -> tuple[float, float]:
    """(interaural delay s, left leads > 0, at the GCC-PHAT peak with parabolic interpolation; energy)."""
    cc, e = gcc_phat(audio, sr, max_itd)
    if e == 0.0:
        return 0.0, 0.0
    lag = (len(cc) - 1) // 2
    k = int(np.argmax(cc))
    frac = 0.0
    if 0 < k < len(cc) - 1:
        a, b, c = cc[k - 1], cc[k], cc[k + 1]
        den = a - 2 * b + c
        frac = 0.5 * (a - c) / den if abs(den) > 1e-12 else 0.0
    return (k - lag + frac) / sr, e


def ego_offsets(size: int, res: float) -> tuple[np.ndarray, np.ndarray]:
    """The metres ahead of and to the left of the robot of each pixel centre of an egocentric image of ``size`` x
    ``size`` pixels of ``res`` m, the robot at the centre facing the top, its left to the left: (fwd, left)."""
    c = (np.arange(size) + 0.5 - size / 2) * res
    return -np.repeat(c[:, None], size, 1), -np.repeat(c[None, :], size, 0)


def draw_route(channel: np.ndarray, p, yaw: float, pts, res: float, value: int = 255) -> None:
    """Draw the polyline ``pts`` (world x, y; its first point is usually the robot's) into ``channel``, an egocentric
    image (H, W) of ``res`` m pixels with the robot at ``p`` (x, y) at the centre facing ``yaw`` degrees to the top,
    its left to the left (:func:`ego_offsets`' frame), at ``value``; what falls outside the image is left out."""
    pts = np.asarray(pts, float)
    seg = [np.linspace(pts[i], pts[i + 1], max(2, int(np.hypot(*(pts[i + 1] - pts[i])) / 0.1) + 1))
           for i in range(len(pts) - 1)]
    if not seg:
        return
    a = math.radians(yaw)
    ca, sa = math.cos(a), math.sin(a)
    q = np.vstack(seg) - np.asarray(p, float)
    f = ca * q[:, 0] + sa * q[:, 1]
    left = -sa * q[:, 0] + ca * q[:, 1]
    H, W = channel.shape
    i = np.floor(H / 2 - f / res).astype(int)
    j = np.floor(W / 2 - left / res).astype(int)
    ok = (i >= 0) & (i < H) & (j >= 0) & (j < W)
    channel[i[ok], j[ok]] = value


def window_cells(grid, x: float, y: float, yaw: float, fwd: np.ndarray, left: np.ndarray):
    """A window of points ``fwd`` m ahead of and ``left`` m to the left of a robot at (``x``, ``y``) facing ``yaw``
    degrees, on ``grid`` (a NavGrid): the points' world x and y (shaped as ``fwd``), and per point (flattened) the
    grid's row and column (clipped into the grid) and whether the point lies inside it."""
    a = math.radians(yaw)
    ca, sa = math.cos(a), math.sin(a)
    wx = x + ca * fwd - sa * left
    wy = y + sa * fwd + ca * left
    rc = grid.cell_of(np.stack([wx.ravel(), wy.ravel()], 1))
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < grid.shape[0]) & (rc[:, 1] >= 0) & (rc[:, 1] < grid.shape[1])
    return wx, wy, np.clip(rc[:, 0], 0, grid.shape[0] - 1), np.clip(rc[:, 1], 0, grid.shape[1] - 1), inside


def project_depth(depth: np.ndarray, p, yaw: float, fx: float, stride: int = 4):
    """Every ``stride``-th pixel of a depth image seen from pose ``p`` (x, y), ``yaw`` degrees: (rows, cols, z the
    depth (H', W'), up the height above the camera, wx, wy the world point); a pinhole of focal length ``fx``
    pixels."""
    H, W = depth.shape
    rows = np.arange(0, H, stride)
    cols = np.arange(0, W, stride)
    z = depth[np.ix_(rows, cols)]
    u = (cols[None, :] - W / 2 + 0.5) / fx
    v = (rows[:, None] - H / 2 + 0.5) / fx
    fwd, left, up = z, -u * z, -v * z
    a = math.radians(yaw)
    wx = p[0] + math.cos(a) * fwd - math.sin(a) * left
    wy = p[1] + math.sin(a) * fwd + math.cos(a) * left
    return rows, cols, z, up, wx, wy


def grid_cells(wx: np.ndarray, wy: np.ndarray, cell: float, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, cols, kept) of the world points (wx, wy) in a ``size`` x ``size`` grid of ``cell`` m centred on the
    odometry origin; ``kept`` marks the points inside it."""
    idx = np.floor(np.stack([wx, wy], 1) / cell).astype(int) + size // 2
    good = (idx >= 0).all(1) & (idx < size).all(1)
    return idx[good, 0], idx[good, 1], good


def map_depth(occ: np.ndarray, depth: np.ndarray, p, yaw: float, fx: float, camera_height: float, cell: float,
              stride: int = 4, floor: np.ndarray | None = None) -> None:
    """Count obstacle hits (points 0.08-0.6 m above the floor) of a depth image into an occupancy grid ``occ``
    (cells of ``cell`` m, centred on the odometry origin) seen from pose ``p`` (x, y), ``yaw`` degrees; with
    ``floor`` (a boolean grid of the same shape) mark the cells where it sees the floor (points below 0.08 m)."""
    _, _, z, up, wx, wy = project_depth(depth, p, yaw, fx, stride)
    ok = z > 0.1
    if not np.any(ok):
        return
    height = camera_height + up
    obst = ok & (height > 0.08) & (height < 0.6)
    size = occ.shape[0]
    np.add.at(occ, grid_cells(wx[obst], wy[obst], cell, size)[:2], 1)
    if floor is not None:
        sel = ok & (height <= 0.08)
        floor[grid_cells(wx[sel], wy[sel], cell, size)[:2]] = True


def grid_field(blocked: np.ndarray, start) -> tuple[np.ndarray, np.ndarray]:
    """8-connected path lengths (in cells) from ``start`` (row, col) over the free cells of a boolean grid, and each
    cell's predecessor on its shortest path (Dijkstra via scipy): (dist, pred), both flat (row * ncols + col);
    unreachable cells have dist inf."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    free = ~blocked
    ny, nx = blocked.shape
    ids = np.arange(ny * nx).reshape(ny, nx)
    src, dst, w = [], [], []
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        r0, r1 = max(0, -dy), ny - max(0, dy)
        c0, c1 = max(0, -dx), nx - max(0, dx)
        m = free[r0:r1, c0:c1] & free[r0 + dy:r1 + dy, c0 + dx:c1 + dx]
        src.append(ids[r0:r1, c0:c1][m])
        dst.append(ids[r0 + dy:r1 + dy, c0 + dx:c1 + dx][m])
        w.append(np.full(int(m.sum()), math.hypot(dy, dx)))
    src, dst, w = np.concatenate(src), np.concatenate(dst), np.concatenate(w)
    g = coo_matrix((np.concatenate([w, w]), (np.concatenate([src, dst]), np.concatenate([dst, src]))),
                   shape=(ny * nx, ny * nx)).tocsr()
    return dijkstra(g, indices=int(start[0]) * nx + int(start[1]), return_predecessors=True)


def grid_trace(pred: np.ndarray, nx: int, start, goal):
    """The cells (row, col) from ``start`` to ``goal`` along :func:`grid_field`'s predecessors; None if the goal was
    not reached."""
    s, t = int(start[0]) * nx + int(start[1]), int(goal[0]) * nx + int(goal[1])
    if t != s and pred[t] < 0:
        return None
    out = [t]
    while out[-1] != s:
        out.append(int(pred[out[-1]]))
    return [(i // nx, i % nx) for i in reversed(out)]


def _grid_path(blocked: np.ndarray, start, goal):
    """8-connected shortest path on a boolean grid (Dijkstra via scipy); list of (row, col) or None."""
    _, pred = grid_field(blocked, start)
    return grid_trace(pred, blocked.shape[1], start, goal)
