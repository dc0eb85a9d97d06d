"""Speaker following (``Sonicverse/SpeakerFollowing-v0``): a person walks a route through several rooms of a home,
speaking now and then (talk and silence spells of several seconds); the robot must keep close using what it hears
(and sees, if given RGB-D), keep following through silences and doors, and stop near the person when they stop at
the end of the route (Catch-Me-If-You-Hear-Me style).

Episode: a home of the split; a route of 3-4 places, each in another room than the one before where the home has
rooms, 6-25 m long in all; the robot starts 1.2-2.2 m (geodesic) from the person, behind them (the first leg of the walk keeps 1 m from it); the person's speed,
voice and speech are drawn from the episode's seed (:mod:`sonicverse_core.world.person`).

Ends (terminated) with ``catch_success`` when, within ``catch_window`` (10 s) of the person stopping, the robot is
within ``catch_radius`` (1 m) geodesic of them and has stopped (it travelled less than 5 cm over the last second); fails
(terminated) when the window passes; truncated at ``max_steps`` (1,200 = 120 s).

Metrics (per episode): ``time_in_band`` (fraction of the steps before the person stops at the end of the route at a
geodesic distance of 1.0-2.5 m from them: after that the robot is meant to close in),
``mean_distance_m`` (geodesic), ``lost_s`` (time beyond 5 m), ``collisions`` (steps with a bump), ``catch_success``,
``time_s``; also the route's length and whether the person reached its end.

Reward per step: +0.1 in the band, -0.02 per metre beyond it (at most 5 m), -``collision_penalty`` on a bump, and
``success_reward`` on a catch.

Privileged state (``env.unwrapped.privileged()``): ``world``, ``person`` (the :class:`~sonicverse_core.world.person.
Person`: position, yaw, route, ``finished``, ``talking()``), ``distance`` (geodesic robot-person, m).

What the robot may know (``env.unwrapped.semantic_map()``): the home's floor plan at the start, its objects, its own
start pose (then odometry); never the person (as in voice retrieval).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sonicverse_core.errors import ConfigError
from sonicverse_core.tasks.base import SemanticMap, Task
from sonicverse_core.tasks.episodes import JsonRecord
from sonicverse_core.world.person import Person, PersonConfig, body_mesh, person_mesh, polyline_points, speech_track

BAND = (1.0, 2.5)
LOST = 5.0
STOP_S = 1.0  # "has stopped": travelled less than 5 cm over this long


@dataclass(frozen=True)
class FollowEpisode(JsonRecord):
    episode_id: str
    scene: str
    split: str
    start: tuple  # robot (x, y, yaw)
    route: tuple  # the person's places ((x, y), ...), the first is where it stands
    speed: float  # m/s
    voice: str
    speech_seed: int
    extra: dict = field(default_factory=dict)


class SpeakerFollowing(Task):
    name = "SpeakerFollowing"
    episode_type = FollowEpisode
    default_sensors = ("depth", "audio", "spectrogram", "bump", "pose")

    def __init__(self, cfg, person: PersonConfig | dict | None = None, route_length=(6.0, 25.0), places=(3, 4),
                 catch_radius: float = 1.0, catch_window: float = 10.0):
        super().__init__(cfg)
        if "pointgoal" in (cfg.sensors or ()):
            raise ConfigError("speaker following has no point goal sensor")
        self.person_cfg = person if isinstance(person, PersonConfig) else PersonConfig(**(person or {}))
        self.route_length = tuple(float(v) for v in route_length)
        self.places = tuple(int(v) for v in places)
        if not (0 < self.route_length[0] <= self.route_length[1]) or not (2 <= self.places[0] <= self.places[1]):
            raise ConfigError("route_length must be an ordered positive range and places at least 2")
        if not (catch_radius > 0 and catch_window > 0):
            raise ConfigError("catch_radius and catch_window must be positive")
        self.catch_radius, self.catch_window = float(catch_radius), float(catch_window)

    # --- episodes ---------------------------------------------------------------------------------------------
    def sample_episode(self, env, rng: np.random.Generator) -> FollowEpisode:
        c = self.cfg
        for _ in range(60):
            spec = env.scene_specs[int(rng.integers(len(env.scene_specs)))]
            w = env.use_home(spec).world
            route = self._route(w, rng)
            if route is None:
                continue
            field_ = w.grid.distance_field(route[0])
            cand = w.grid.sample(rng, 300)
            geo = w.grid.geodesic_from_field(field_, cand)
            # behind the person: the first stretch of its walk keeps at least 1 m from the robot
            leg, _ = w.grid.shortest_path(route[0], route[1])
            pts = polyline_points(leg, 0.1)
            ok = np.flatnonzero((geo >= 1.2) & (geo <= 2.2))
            clear = [i for i in ok if np.min(np.linalg.norm(pts[1:] - cand[i], axis=1)) >= 1.0]
            if not clear:
                continue
            ok = clear
            s = cand[int(ok[0])]
            yaw = float(rng.uniform(-180.0, 180.0))
            pc = self.person_cfg
            return FollowEpisode("", spec, c.split, (float(s[0]), float(s[1]), yaw),
                                 tuple((float(x), float(y)) for x, y in route), float(rng.uniform(*pc.speed)),
                                 pc.voices[int(rng.integers(len(pc.voices)))], int(rng.integers(2 ** 31)))
        raise ConfigError("no speaker-following route could be sampled in these homes")

    def _route(self, w, rng) -> np.ndarray | None:
        rooms = [r.name for r in w.scene.rooms] or [None]
        k = int(rng.integers(self.places[0], self.places[1] + 1))
        room = rooms[int(rng.integers(len(rooms)))]
        pts = [w.grid.sample(rng, 1, room=room)[0] if room else w.grid.sample(rng)[0]]
        total = 0.0
        for _ in range(k - 1):
            others = [r for r in rooms if r != room] or rooms
            room = others[int(rng.integers(len(others)))]
            cand = w.grid.sample(rng, 16, room=room) if room else w.grid.sample(rng, 16)
            geo = w.grid.geodesic_from_field(w.grid.distance_field(pts[-1]), cand)
            ok = np.flatnonzero(np.isfinite(geo) & (geo >= 2.0))
            if len(ok) == 0:
                return None
            pts.append(cand[int(ok[0])])
            total += float(geo[int(ok[0])])
        lo, hi = self.route_length
        return np.array(pts) if lo <= total <= hi else None

    def reset(self, env, rng, options):
        ep = self.episode(env, rng, options)
        w = env.use_home(ep.scene).world
        self.person = p = Person(w, ep.route, self.person_cfg, speed=ep.speed, rng=np.random.default_rng(ep.speech_seed))
        w.place_robot(*ep.start)
        w.bodies["person"] = (p.pos.copy(), p.cfg.radius)
        env.new_renderer()
        seconds = self.cfg.max_steps * self.cfg.step_seconds + 1.0
        track, p.spans = speech_track(seconds, self.cfg.sample_rate, np.random.default_rng(ep.speech_seed),
                                      p.cfg, ep.voice)
        env.source = env.add_sound(track, loop=False, position=p.mouth, directivity=p.cfg.directivity,
                                   forward=p.forward)
        env.add_actor("person", person_mesh(p.cfg.height, p.cfg.radius))
        env.move_actor("person", p.pose)
        self.distances: list[float] = []
        self.walking: list[bool] = []  # per step: the person had not yet stopped at the end of the route
        self.travelled: list[float] = [0.0]  # the robot's path length after each step
        self._field_key = None
        self.caught = False
        self.dist = self._distance(env)
        self.map = SemanticMap.of(w, ep.start)
        return ep

    def semantic_map(self, env) -> SemanticMap:
        return self.map

    # --- per step ---------------------------------------------------------------------------------------------
    def _distance(self, env) -> float:
        """Geodesic robot-person distance (m); the person's distance field is recomputed when it changes cell."""
        w = env.home.world
        key = tuple(w.grid.cell_of(self.person.pos)[0])
        if key != self._field_key:
            self._field = w.grid.distance_field(self.person.pos)
            self._field_key = key
        d = float(w.grid.geodesic_from_field(self._field, w.pose[None, :2])[0])
        return d if np.isfinite(d) else float(np.hypot(*(w.pose[:2] - self.person.pos)))

    def advance(self, env, dt):
        p, w = self.person, env.home.world
        p.advance(dt, robot_gap=self.dist, robot_xy=w.pose[:2], robot_radius=w.robot.radius)
        w.bodies["person"] = (p.pos.copy(), p.cfg.radius)
        env.source.position = p.mouth
        env.source.forward = p.forward
        env.move_actor("person", p.pose)

    def evaluate(self, env, a):
        d = self.dist = self._distance(env)
        self.distances.append(d)
        self.walking.append(not self.person.finished)
        self.travelled.append(env.path_length)
        c, p = self.cfg, self.person
        reward = 0.1 if BAND[0] <= d <= BAND[1] else -0.02 * min(max(d - BAND[1], 0.0), LOST)
        reward -= c.collision_penalty * env.home.world.bumped
        success = terminated = False
        if p.finished:
            since = p.t - p.stop_time
            if d <= self.catch_radius and self._stopped(env):
                success = terminated = self.caught = True
                reward += c.success_reward
            elif since >= self.catch_window:
                terminated = True
        return reward, terminated, success

    def _stopped(self, env) -> bool:
        """The robot has stopped: it travelled less than 5 cm (path length) over the last second."""
        n = max(1, int(round(STOP_S / self.cfg.step_seconds)))
        if len(self.travelled) < n + 1:
            return False
        return self.travelled[-1] - self.travelled[-1 - n] < 0.05

    def info(self, env) -> dict:
        return {"distance_to_person": self.dist, "person_finished": self.person.finished}

    def metrics(self, env, success: bool) -> dict:
        d = np.asarray(self.distances or [self.dist], float)
        follow = d[np.asarray(self.walking, bool)] if any(self.walking) else d
        dt = self.cfg.step_seconds
        return {"catch_success": float(success), "success": float(success),
                "time_in_band": float(np.mean((follow >= BAND[0]) & (follow <= BAND[1]))),
                "mean_distance_m": float(d.mean()), "lost_s": float(np.sum(d > LOST) * dt),
                "collisions": env.collisions, "time_s": env.steps * dt, "steps": env.steps,
                "route_length": self.person.length, "person_finished": float(self.person.finished),
                "path_length": env.path_length}

    def privileged(self, env) -> dict:
        return {"world": env.home.world, "person": self.person, "distance": self.dist}
