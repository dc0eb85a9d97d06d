"""A person in the world: a body the robot collides with and its camera sees, a mouth at head height that speaks
with speech directivity, walking the home along navigable paths at human speeds, pausing at the places it visits,
turning at a human rate, and speaking utterances from a phrase list now and then (espeak-ng offline).

Walking: the route is a list of places; between them the person follows the geodesic shortest path of the floor
(string-pulled, through open doors) at a speed drawn per episode from :attr:`PersonConfig.speed` (indoor walking:
1.0-1.4 m/s), turns on the spot when the next leg bends by more than 60 degrees (at ``turn_deg_s``), pauses at each
intermediate place and stops for good at the last. A TurtleBot's top speed (0.7 m/s) is about half a walking pace,
so a person who leads a robot keeps to its pace, as a guide does: when the robot is more than ``pace_gap`` m behind
(geodesic, as told by the task) the person slows to ``pace_speed`` (0.5 m/s: a robot that follows gains on them);
when it is more than ``escort_gap`` m behind (past the following band's 2.5 m) they stop until it is within
``escort_resume`` m, at most ``max_wait_s`` at a time; after a wait that ran out they walk on for as long again
before waiting again (a robot that is lost does not hold the person forever). A robot that does not follow gains
nothing from the waits: they begin outside the band. The person
also waits (at most 1 s) rather than walk into the robot, then squeezes past (the robot may always move away from a body
that came onto it).

Speech: alternating talk and silence spells of several seconds (:attr:`talk_s`, :attr:`silence_s`), starting with
talk; a talk spell is a run of phrases with short gaps, in one voice per episode. The whole track is made in advance
(the voice is a pre-recorded person in this sense), and :meth:`Person.talking` says when it speaks.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from sonicverse_core.errors import ConfigError

PHRASES = ("follow me please", "this way", "come along", "i am over here", "keep up with me", "can you hear me",
           "over here robot", "let us go", "stay close to me", "we are almost there", "turn here", "not far now")
VOICES = ("en-us", "en-us+f2", "en-gb", "en-us+m3", "en-gb-x-rp", "en-029")
SPEEDS = (140, 165)  # espeak-ng words per minute


@dataclass(frozen=True)
class PersonConfig:
    radius: float = 0.22  # m: shoulders
    height: float = 1.72  # m
    mouth_height: float = 1.58  # m above the floor
    speed: tuple = (1.0, 1.4)  # m/s, drawn per episode
    turn_deg_s: float = 200.0  # turning on the spot
    pause_s: tuple = (1.0, 3.0)  # at each intermediate place
    talk_s: tuple = (2.0, 5.0)  # a talk spell
    silence_s: tuple = (2.0, 5.0)  # a silence between spells
    phrase_gap_s: tuple = (0.2, 0.6)
    speech_peak: float = 0.5  # each utterance's peak (about 70 dB SPL at 1 m with the renderer's reference)
    directivity: float = 0.3  # gain (1 - a) + a cos(angle): -3 dB to the sides, -8 dB behind (broadband speech)
    pace_gap: float = 1.6  # m: slow to ``pace_speed`` when the robot is farther behind
    pace_speed: float = 0.5  # m/s: a pace a TurtleBot (0.7 m/s) gains on
    escort_gap: float = 2.6  # m: wait for a robot farther behind (outside the following band)
    escort_resume: float = 1.8  # m: walk on when it is this close
    max_wait_s: float = 3.0  # at a time
    voices: tuple = VOICES

    def __post_init__(self):
        lo, hi = self.speed
        if not (0.1 <= lo <= hi <= 3.0):
            raise ConfigError(f"person speed must be within 0.1-3 m/s, got {self.speed}")
        if not (0 < self.mouth_height < self.height <= 2.5 and 0.1 <= self.radius <= 0.5):
            raise ConfigError("person needs 0 < mouth_height < height <= 2.5 m and a radius of 0.1-0.5 m")
        for name in ("pause_s", "talk_s", "silence_s", "phrase_gap_s"):
            lo, hi = getattr(self, name)
            if not (0 <= lo <= hi <= 600):
                raise ConfigError(f"person {name} must be an ordered range of 0-600 s, got {(lo, hi)}")
        if not (0 < self.pace_gap and 0 < self.pace_speed <= 3.0 and 0 < self.escort_resume <= self.escort_gap
                and self.max_wait_s >= 0):
            raise ConfigError("person needs pace_gap > 0, 0 < pace_speed <= 3 m/s, 0 < escort_resume <= escort_gap "
                              "and max_wait_s >= 0")
        if not self.voices:
            raise ConfigError("person needs at least one voice")


@lru_cache(maxsize=256)
def utterance(text: str, voice: str, speed: int, sample_rate: int, peak: float) -> np.ndarray:
    """One phrase from espeak-ng (disk-cached), trimmed of its padding, scaled to ``peak``; read-only."""
    from assets_manifest.speech import speak

    x, _ = speak(text, voice=voice, speed=speed, pad_s=0.0, sample_rate=sample_rate)
    x = x / max(float(np.abs(x).max()), 1e-9) * peak
    x = x.astype(np.float32)
    x.setflags(write=False)
    return x


def speech_track(seconds: float, sample_rate: int, rng: np.random.Generator, cfg: PersonConfig,
                 voice: str) -> tuple[np.ndarray, list[tuple[float, float]]]:
    """(mono track, [(start_s, end_s) of each utterance]) of talk and silence spells, starting with talk."""
    n = int(seconds * sample_rate)
    out = np.zeros(n, np.float32)
    spans: list[tuple[float, float]] = []
    t = 0.0
    while t < seconds:
        spell_end = t + rng.uniform(*cfg.talk_s)
        while t < spell_end and t < seconds:
            u = utterance(PHRASES[int(rng.integers(len(PHRASES)))], voice, int(SPEEDS[int(rng.integers(len(SPEEDS)))]),
                          sample_rate, cfg.speech_peak)
            i = int(t * sample_rate)
            k = min(len(u), n - i)
            if k <= 0:
                break
            out[i:i + k] = u[:k]
            spans.append((t, t + k / sample_rate))
            t += len(u) / sample_rate + rng.uniform(*cfg.phrase_gap_s)
        t += rng.uniform(*cfg.silence_s)
    return out, spans


def polyline_points(path: np.ndarray, spacing: float = 0.1, metres: float = np.inf) -> np.ndarray:
    """Points every ``spacing`` m along a polyline (k, 2), up to ``metres`` from its start."""
    path = np.asarray(path, float)
    if len(path) < 2:
        return path.copy()
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.arange(0.0, min(s[-1], metres) + 1e-9, spacing)
    return np.stack([np.interp(t, s, path[:, 0]), np.interp(t, s, path[:, 1])], 1)


@lru_cache(maxsize=8)
def person_mesh(height: float, radius: float, shirt=(70, 100, 150)):
    """A person's body built from parts (legs, shoes, hips, torso, shoulders, arms, hands, neck, head, hair, nose:
    :func:`sonicverse_core.scene.furniture.person`) as one mesh with its parts' face colours, in the local frame of
    :func:`body_mesh` (feet at z = 0, facing +x): what the robot's camera sees of the person."""
    import trimesh

    from sonicverse_core.scene.furniture import person

    parts = person(height, radius, shirt=shirt)
    mesh = trimesh.util.concatenate([p.mesh for p in parts])
    mesh.visual.face_colors = np.concatenate([np.tile(np.asarray(p.colour, np.uint8), (len(p.mesh.faces), 1))
                                              for p in parts])
    return mesh


@lru_cache(maxsize=8)
def body_mesh(height: float, radius: float):
    """A person's body in its local frame (feet at z = 0, facing +x): legs and torso as a capsule-like cylinder, a
    head, and a nose that shows which way it faces."""
    import trimesh

    torso = trimesh.creation.cylinder(radius=radius * 0.8, height=height - 0.25, sections=16)
    torso.apply_translation([0, 0, (height - 0.25) / 2])
    shoulders = trimesh.creation.box([radius * 1.2, radius * 2.0, 0.5])
    shoulders.apply_translation([0, 0, height - 0.55])
    head = trimesh.creation.icosphere(subdivisions=2, radius=0.11)
    head.apply_translation([0, 0, height - 0.12])
    nose = trimesh.creation.box([0.06, 0.04, 0.04])
    nose.apply_translation([0.12, 0, height - 0.14])
    return trimesh.util.concatenate([torso, shoulders, head, nose])


class Person:
    """A person walking ``route`` (places (k, 2), the first is where it stands) in ``world``."""

    def __init__(self, world, route, cfg: PersonConfig = PersonConfig(), rng: np.random.Generator | None = None,
                 speed: float | None = None):
        rng = rng if rng is not None else np.random.default_rng(0)
        self.world, self.cfg = world, cfg
        route = np.asarray(route, float)
        if route.ndim != 2 or route.shape[1] != 2 or len(route) < 1 or not np.all(np.isfinite(route)):
            raise ConfigError("a person's route must be (k >= 1, 2) finite places")
        legs = []
        for a, b in zip(route[:-1], route[1:]):
            path, length = world.grid.shortest_path(a, b)
            if not np.isfinite(length):
                raise ConfigError(f"a person cannot walk from {a.round(2).tolist()} to {b.round(2).tolist()}")
            legs.append(path)
        self.route = route
        self.legs = legs
        self.speed = float(speed if speed is not None else rng.uniform(*cfg.speed))
        self.pauses = [float(rng.uniform(*cfg.pause_s)) for _ in range(max(len(legs) - 1, 0))]
        self.length = float(sum(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)) for p in legs))
        self.pos = route[0].copy()
        first = legs[0][1] - legs[0][0] if legs and len(legs[0]) > 1 else np.array([1.0, 0.0])
        self.yaw = math.degrees(math.atan2(first[1], first[0]))
        self.t = 0.0
        self.leg, self.k = 0, 1  # current leg and its next waypoint
        self.pause_left = 0.0
        self.waited = 0.0  # the current escort wait
        self._waiting = False
        self.walk_on = 0.0
        self.blocked_for = 0.0
        self.stop_time: float | None = 0.0 if not legs else None
        self.walked = 0.0
        self.spans: list[tuple[float, float]] = []

    # --- state ------------------------------------------------------------------------------------------------
    @property
    def finished(self) -> bool:
        return self.stop_time is not None

    @property
    def walking(self) -> bool:
        return self._moving

    _moving = False

    @property
    def escorting(self) -> bool:
        """Waiting for the robot to catch up."""
        return self._waiting

    @property
    def z_floor(self) -> float:
        return self.world.base.z_floor

    @property
    def mouth(self) -> np.ndarray:
        return np.array([self.pos[0], self.pos[1], self.z_floor + self.cfg.mouth_height])

    @property
    def forward(self) -> np.ndarray:
        a = math.radians(self.yaw)
        return np.array([math.cos(a), math.sin(a), 0.0])

    @property
    def pose(self) -> np.ndarray:
        """4x4 world pose of the body (feet on the floor, facing ``yaw``)."""
        from sonicverse_core.scene.model import yaw_pose

        return yaw_pose(self.pos[0], self.pos[1], self.z_floor, self.yaw)

    def upcoming(self, metres: float, spacing: float = 0.1) -> np.ndarray:
        """(n, 2) points along the rest of the route for the next ``metres`` (the current place first)."""
        pts = [self.pos]
        if not self.finished:
            pts += list(self.legs[self.leg][self.k:])
            for leg in self.legs[self.leg + 1:]:
                pts += list(leg[1:])
        return polyline_points(np.array(pts), spacing, metres)

    def talking(self, t: float | None = None) -> bool:
        t = self.t if t is None else t
        return any(a <= t < b for a, b in self.spans)

    # --- motion -----------------------------------------------------------------------------------------------
    def _turn_towards(self, heading: float, dt: float) -> float:
        """Turn towards ``heading`` (deg) for up to dt s; returns the time left over."""
        err = (heading - self.yaw + 180.0) % 360.0 - 180.0
        rate = self.cfg.turn_deg_s
        need = abs(err) / rate
        if need <= dt:
            self.yaw = heading
            return dt - need
        self.yaw += math.copysign(rate * dt, err)
        return 0.0

    def advance(self, dt: float, robot_gap: float | None = None, robot_xy=None, robot_radius: float = 0.18) -> None:
        """Walk for ``dt`` s. ``robot_gap``: the robot's geodesic distance behind (for escorting)."""
        self.t += dt
        self._moving = False
        if self.finished:
            return
        if self.pause_left > 0:
            self.pause_left = max(0.0, self.pause_left - dt)
            return
        far = robot_gap is not None and np.isfinite(robot_gap) and robot_gap > self.cfg.escort_gap
        if self.walk_on > 0:  # walking on after a wait that ran out: no new wait for a while
            self.walk_on = max(0.0, self.walk_on - dt)
        elif self._waiting or far:
            resume = robot_gap is None or not np.isfinite(robot_gap) or robot_gap <= self.cfg.escort_resume
            if self.waited >= self.cfg.max_wait_s:
                self.walk_on, self.waited, self._waiting = self.cfg.max_wait_s, 0.0, False
            elif not resume:
                self.waited += dt
                self._waiting = True
                return
            else:
                self.waited, self._waiting = 0.0, False
        path = self.legs[self.leg]
        target = path[self.k]
        d = target - self.pos
        heading = math.degrees(math.atan2(d[1], d[0])) if np.hypot(*d) > 1e-9 else self.yaw
        err = (heading - self.yaw + 180.0) % 360.0 - 180.0
        left = dt
        if abs(err) > 60.0:  # a sharp bend: turn on the spot first
            left = self._turn_towards(heading, dt)
            if left <= 0:
                return
        else:
            self._turn_towards(heading, dt)
        if robot_xy is not None:  # do not walk into the robot: wait a moment, then step on
            r = np.asarray(robot_xy, float)[:2] - self.pos
            dist = float(np.hypot(*r))
            ahead = dist > 0 and float(np.dot(r, d)) / (dist * max(np.hypot(*d), 1e-9)) > 0.3
            if ahead and dist < self.cfg.radius + robot_radius + 0.15 and self.blocked_for < 1.0:
                self.blocked_for += dt
                return
            if not (ahead and dist < self.cfg.radius + robot_radius + 0.15):
                self.blocked_for = 0.0
        speed = self.speed
        if robot_gap is not None and np.isfinite(robot_gap) and robot_gap > self.cfg.pace_gap:
            speed = min(speed, self.cfg.pace_speed)  # the robot lags: walk at a pace it can keep
        step = speed * left
        self._moving = step > 0
        while step > 0:
            seg = path[self.k] - self.pos
            L = float(np.hypot(*seg))
            if step < L:
                self.pos = self.pos + seg * (step / L)
                self.walked += step
                break
            self.pos = path[self.k].copy()
            self.walked += L
            step -= L
            self.k += 1
            if self.k >= len(path):  # end of the leg: pause, or stop for good at the last place
                if self.leg + 1 >= len(self.legs):
                    self.stop_time = self.t
                    return
                self.pause_left = self.pauses[self.leg]
                self.leg, self.k = self.leg + 1, 1
                return
            nxt = path[self.k] - self.pos
            if abs((math.degrees(math.atan2(nxt[1], nxt[0])) - self.yaw + 180.0) % 360.0 - 180.0) > 60.0:
                return  # the bend is sharp: turn on the spot in the next step
