"""Voice-driven object retrieval (``Sonicverse/VoiceRetrieval-v0``): a person somewhere in the home asks for an
object the robot can carry ("please bring me the cushion"); the robot, possibly in another room, must understand the
command from what reaches its ears, go to an object of that category, pick it up, bring it to the person and put it
down within 1 m of them.

Episode: a home of the split; a category among the home's carriable objects (any object of it will do); the person
standing at a navigable point at least 2 m (geodesic) from every object of that category, facing a random way; the
robot 2-12 m (geodesic) from the person, anywhere. The person's voice (one of the person's voices, which the
recogniser was not trained on), speed and command wording are drawn from the episode's seed. The person says the
command 0.5 s into the episode and again every ``repeat_s`` (8 s) until the robot picks something up; from then on
they call ("over here", "i am here", ...) every ``call_s`` (3 s) so the robot can find them.

Actions: the two wheel velocities and ``interact`` (the third component > 0): pick up the nearest carriable object
within reach (0.5 m from the robot's edge) that lies most nearly straight ahead when carrying nothing, else put the carried object down in front of the
robot. An interaction that cannot happen (nothing in reach, no room to put it down) changes nothing. Putting an
object down ends the episode (terminated): a success when it is of the asked category and its centre lies within
``place_radius`` (1 m) of the person. Truncated at ``max_steps`` (900 = 90 s).

Metrics (per episode): ``sr``; ``spl`` over the whole route (the shortest route is the geodesic from the robot's
start to the nearest object of the category and from there to the person); ``command_accuracy`` (the first object
the robot picked up is of the asked category: it understood the command); ``time_s``; ``collisions``.

Reward per step: -``step_penalty``, -``collision_penalty`` on a bump, +1 for picking up an object of the asked
category, ``success_reward`` on success.

Privileged state (``env.unwrapped.privileged()``): ``world``, ``person`` (x, y), ``category``, ``text`` (the
command), ``targets`` (names of the objects of the category).

What the robot may know (``env.unwrapped.semantic_map()``, :class:`~sonicverse_core.tasks.base.SemanticMap`): the
home's floor plan as it stands at the start, every object with its category and bounds, and its own start pose on
that map; not the person, not the command.

Estimates (``env.unwrapped.report(speaker=(x, y))``, map frame): where the agent believes the speaker stands. The
first report is scored against the robot's pose at that moment: ``speaker_azimuth_error_deg`` (the angle at the
robot between the estimate and the mouth), ``speaker_distance_error_m`` (the difference of their straight-line
distances); NaN (left out of the means) when an agent reports nothing. ``same_room`` says whether the robot and the
person were in the same room then (the issue's azimuth target is for the same room).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sonicverse_core.errors import ActionError, ConfigError
from sonicverse_core.tasks.base import SemanticMap, Task
from sonicverse_core.tasks.episodes import JsonRecord
from sonicverse_core.world.person import SPEEDS, VOICES, PersonConfig, body_mesh, person_mesh, utterance

CALLS = ("over here", "i am over here", "here please", "bring it here")
#: how a person asks for an object, and names each category of the homes (the recogniser's vocabulary too)
TEMPLATES = ("please bring me the {}", "bring me the {}", "fetch me the {}", "get me the {}", "can you bring me the {}",
             "please fetch the {}", "i need the {}", "could you get me the {}")
SPOKEN = {"straight_chair": "chair", "breakfast_table": "table", "picture": "picture", "bottom_cabinet": "cabinet",
          "cushion": "cushion", "sofa": "sofa", "bed": "bed", "shelf": "shelf", "sink": "sink", "toilet": "toilet",
          "stool": "stool", "standing_tv": "television", "shower": "shower", "bathtub": "bathtub",
          "countertop": "countertop"}


@dataclass(frozen=True)
class RetrievalEpisode(JsonRecord):
    episode_id: str
    scene: str
    split: str
    start: tuple  # robot (x, y, yaw)
    person: tuple  # (x, y, yaw)
    category: str
    text: str
    voice: str
    speed: int
    extra: dict = field(default_factory=dict)


def _track(seconds: float, sr: int, first: np.ndarray, every: float, start: float) -> np.ndarray:
    out = np.zeros(int(seconds * sr), np.float32)
    t = start
    while t < seconds:
        i = int(t * sr)
        n = min(len(first), len(out) - i)
        out[i:i + n] += first[:n]
        t += max(every, len(first) / sr + 0.5)
    return out


def approach_points(w, name: str, reach: float = 0.45) -> np.ndarray:
    """(k, 2) navigable cell centres from which the robot can pick up object ``name`` (its edge within ``reach``
    of the object's footprint)."""
    lo, hi = w.scene.object(name).world_bounds()[:, :2]
    return approach_cells(w.grid, lo, hi, w.robot.radius + reach)


def approach_cells(g, lo, hi, r: float) -> np.ndarray:
    """(k, 2) navigable cell centres of grid ``g`` within ``r`` m of the box ``lo``-``hi`` (x, y)."""
    lo, hi = np.asarray(lo, float)[:2], np.asarray(hi, float)[:2]
    rc0, rc1 = g.cell_of(lo - r)[0], g.cell_of(hi + r)[0]
    rr, cc = np.mgrid[rc0[0]:rc1[0] + 1, rc0[1]:rc1[1] + 1]
    xy = g.center_of(np.c_[rr.ravel(), cc.ravel()])
    gap = np.hypot(*np.maximum(np.maximum(lo - xy, xy - hi), 0.0).T)
    xy = xy[gap <= r]
    return xy[g.is_navigable(xy)] if len(xy) else xy


class VoiceRetrieval(Task):
    name = "VoiceRetrieval"
    episode_type = RetrievalEpisode
    default_sensors = ("depth", "audio", "spectrogram", "bump", "pose")
    stop_action = True  # the third action component: interact (pick up / put down)

    def __init__(self, cfg, repeat_s: float = 8.0, call_s: float = 3.0, place_radius: float = 1.0,
                 distance=(2.0, 12.0), person: PersonConfig | dict | None = None):
        super().__init__(cfg)
        if "pointgoal" in (cfg.sensors or ()):
            raise ConfigError("voice retrieval has no point goal sensor")
        if not (repeat_s > 0 and call_s > 0 and place_radius > 0 and 0 < distance[0] <= distance[1]):
            raise ConfigError("repeat_s, call_s and place_radius must be positive and distance an ordered range")
        self.repeat_s, self.call_s, self.place_radius = float(repeat_s), float(call_s), float(place_radius)
        self.distance = (float(distance[0]), float(distance[1]))
        self.person_cfg = person if isinstance(person, PersonConfig) else PersonConfig(**(person or {}))

    def sample_episode(self, env, rng: np.random.Generator) -> RetrievalEpisode:
        for _ in range(60):
            spec = env.scene_specs[int(rng.integers(len(env.scene_specs)))]
            w = env.use_home(spec).world
            cats = sorted({o.category for o in w.scene.objects if o.movable and o.category in SPOKEN})
            if not cats:
                continue
            cat = cats[int(rng.integers(len(cats)))]
            names = [o.name for o in w.scene.objects if o.movable and o.category == cat]
            pts = [approach_points(w, n) for n in names]
            if not any(len(q) for q in pts):
                continue
            p = w.grid.sample(rng, 1)[0]
            f = w.grid.distance_field(p)
            near = [np.min(w.grid.geodesic_from_field(f, q)) for q in pts if len(q)]
            if not np.isfinite(min(near)) or min(near) < 2.0 or np.min(np.hypot(*(np.array(
                    [w.scene.object(n).position[:2] for n in names]) - p).T)) < 2.0:
                continue
            cand = w.grid.sample(rng, 64)
            geo = w.grid.geodesic_from_field(f, cand)
            ok = np.flatnonzero((geo >= self.distance[0]) & (geo <= self.distance[1]))
            if len(ok) == 0:
                continue
            s = cand[int(ok[0])]
            voice = VOICES[int(rng.integers(len(VOICES)))]
            text = TEMPLATES[int(rng.integers(len(TEMPLATES)))].format(SPOKEN[cat])
            return RetrievalEpisode("", spec, self.cfg.split, (float(s[0]), float(s[1]), float(rng.uniform(-180, 180))),
                                    (float(p[0]), float(p[1]), float(rng.uniform(-180, 180))), cat, text, voice,
                                    int(SPEEDS[int(rng.integers(len(SPEEDS)))]))
        raise ConfigError("no voice-retrieval episode could be sampled in these homes")

    def reset(self, env, rng, options):
        ep = self.episode(env, rng, options)
        w = env.use_home(ep.scene).world
        w.place_robot(*ep.start)
        pc = self.person_cfg
        self.person_xy = np.array(ep.person[:2], float)
        w.bodies["person"] = (self.person_xy.copy(), pc.radius)
        env.new_renderer()
        z = w.base.z_floor
        a = np.radians(ep.person[2])
        mouth = (self.person_xy[0], self.person_xy[1], z + pc.mouth_height)
        fwd = (float(np.cos(a)), float(np.sin(a)), 0.0)
        sr, seconds = self.cfg.sample_rate, self.cfg.max_steps * self.cfg.step_seconds + 1.0
        command = np.array(utterance(ep.text, ep.voice, ep.speed, sr, pc.speech_peak))
        call = np.concatenate([np.array(utterance(c, ep.voice, ep.speed, sr, pc.speech_peak)) for c in CALLS[:2]])
        env.source = env.add_sound(_track(seconds, sr, command, self.repeat_s, 0.5), loop=False, position=mouth,
                                   directivity=pc.directivity, forward=fwd)
        self.calls = env.add_sound(_track(seconds, sr, call, self.call_s, 0.0), loop=False, position=mouth,
                                   directivity=pc.directivity, forward=fwd, gain=0.0)
        env.add_actor("person", person_mesh(pc.height, pc.radius))
        pose = np.eye(4)
        pose[:3, 3] = (self.person_xy[0], self.person_xy[1], z)
        env.move_actor("person", pose)
        self.targets = [o.name for o in w.scene.objects if o.movable and o.category == ep.category]
        # the shortest route: start -> a place to pick up an object of the category -> the person
        f_p, f_r = w.grid.distance_field(self.person_xy), w.grid.distance_field(np.array(ep.start[:2]))
        self.shortest = np.inf
        for n in self.targets:
            q = approach_points(w, n)
            if len(q):
                via = w.grid.geodesic_from_field(f_r, q) + w.grid.geodesic_from_field(f_p, q)
                self.shortest = min(self.shortest, float(np.min(via)))
        self.first_pick: str | None = None
        self.placed: str | None = None
        self.understood = False
        self.map = SemanticMap.of(w, ep.start)
        self.estimate: tuple | None = None  # (estimate xy, robot xy, room shared) at the first report
        return ep

    def semantic_map(self, env) -> SemanticMap:
        return self.map

    def report(self, env, estimates: dict) -> None:
        unknown = set(estimates) - {"speaker"}
        if unknown:
            raise ConfigError(f"voice retrieval scores only 'speaker', not {', '.join(sorted(unknown))}")
        xy = np.asarray(estimates["speaker"], float)
        if xy.shape != (2,) or not np.all(np.isfinite(xy)):
            raise ConfigError(f"speaker must be a finite (x, y), got {estimates['speaker']!r}")
        if self.estimate is None:
            w = env.home.world
            ra, rb = w.scene.room_at(w.pose[:2]), w.scene.room_at(self.person_xy)
            self.estimate = (xy, w.pose[:2].copy(), ra is not None and ra is rb)

    def evaluate(self, env, a):
        c, w = self.cfg, env.home.world
        reward = -c.step_penalty - c.collision_penalty * w.bumped
        if a[2] <= 0:
            return reward, False, False
        if w.carried is None:
            name = self._in_front(w)
            if name is not None:
                try:
                    w.pick(name)
                except ActionError:
                    return reward, False, False
                if self.first_pick is None:
                    self.first_pick = name
                    self.understood = name in self.targets
                    reward += 1.0 if self.understood else 0.0
                env.source.gain = 0.0  # the person stops asking and starts calling
                self.calls.gain = 1.0
            return reward, False, False
        try:
            name = w.place()
        except ActionError:
            return reward, False, False
        self.placed = name
        d = float(np.hypot(*(w.scene.object(name).position[:2] - self.person_xy)))
        success = name in self.targets and d <= self.place_radius
        return reward + (c.success_reward if success else 0.0), True, success

    @staticmethod
    def _in_front(w) -> str | None:
        """The carriable object within reach that lies most nearly straight ahead of the robot (None: none)."""
        best, name = None, None
        a = np.radians(w.pose[2])
        for o in w.scene.objects:
            if not o.movable or w.reach_distance(o.name) > 0.5:
                continue
            v = o.position[:2] - w.pose[:2]
            ang = abs(float(np.arctan2(v[1], v[0]) - a + np.pi) % (2 * np.pi) - np.pi)
            if best is None or ang < best:
                best, name = ang, o.name
        return name

    def info(self, env) -> dict:
        w = env.home.world
        return {"carrying": w.carried, "distance_to_person": float(np.hypot(*(w.pose[:2] - self.person_xy)))}

    def metrics(self, env, success: bool) -> dict:
        from sonicverse_core.tasks.metrics import spl

        az = dist = float("nan")
        same = float("nan")
        if self.estimate is not None:
            est, robot, shared = self.estimate
            a, b = est - robot, self.person_xy - robot
            az = abs((np.degrees(np.arctan2(a[1], a[0]) - np.arctan2(b[1], b[0])) + 180.0) % 360.0 - 180.0)
            dist = abs(float(np.hypot(*a)) - float(np.hypot(*b)))
            same = float(shared)
        return {"sr": float(success), "success": float(success),
                "spl": spl(success, self.shortest, env.path_length),
                "command_accuracy": float(self.understood), "speaker_azimuth_error_deg": float(az),
                "speaker_distance_error_m": dist, "same_room": same, "time_s": env.steps * self.cfg.step_seconds,
                "collisions": env.collisions, "steps": env.steps, "path_length": env.path_length,
                "shortest_m": self.shortest}

    def privileged(self, env) -> dict:
        ep = env.episode
        return {"world": env.home.world, "person": self.person_xy.copy(), "category": ep.category, "text": ep.text,
                "targets": list(self.targets)}
