"""Agents for voice-driven retrieval (sonicverse_core/tasks/retrieval.py).

* ``oracle`` (privileged: ``world``, ``person``, ``targets``): drives the geodesic shortest path to the nearest object
  of the asked category, picks it up, drives to the person, turns to face them and puts it down; proves the metrics
  (SR and SPL near 1).
* ``random``: the navigation tasks' random agent (uniform wheel velocities; it never interacts).
"""
from __future__ import annotations

import math

import numpy as np

from agents.scripted import Agent, _pursue, _wheels

REACH = 0.45  # m: a little inside the world's 0.5 m reach
HAND_OVER = 0.85  # m from the person: the object goes down about 0.4 m in front of the robot


class OracleRetriever(Agent):
    name = "oracle"

    def reset(self, env, obs, info):
        super().reset(env, obs, info)
        priv = env.privileged()
        w = priv["world"]
        from sonicverse_core.tasks.retrieval import approach_points

        f = w.grid.distance_field(w.pose[:2])
        best = (np.inf, None, None)
        for n in priv["targets"]:
            q = approach_points(w, n, REACH)
            if len(q):
                g = w.grid.geodesic_from_field(f, q)
                k = int(np.argmin(g))
                best = min(best, (float(g[k]), n, q[k]), key=lambda t: t[0])
        _, self.target, self.spot = best
        self.path, self.k, self.goal = None, 1, None
        self.tries = 0  # put-downs tried at the person (no room in front: turn a little and try again)
        self.hand_spot, self.tried = None, []

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
        v = np.asarray(xy) - w.pose[:2]
        err = (math.degrees(math.atan2(v[1], v[0])) + offset - w.pose[2] + 180.0) % 360.0 - 180.0
        if abs(err) < 8.0:
            return np.zeros(2), True
        rate = math.copysign(min(abs(math.radians(err)) / self.dt * 0.8, math.radians(self.robot.max_turn_deg)), err)
        return _wheels(0.0, rate, self.robot), False

    def act(self, obs, info):
        priv = self.env.privileged()
        w, person = priv["world"], priv["person"]
        if w.carried is None:
            if self.target is None:  # no place to pick one up from
                return self._out([0.0, 0.0])
            if w.reach_distance(self.target) <= REACH:
                wheels, facing = self._face(w, w.scene.object(self.target).position[:2])
                return self._out(wheels, stop=facing)
            return self._out(self._follow(w, self.spot, slow=0.3))
        if self.tries >= 15:  # no room to put it down from here: hand over from another side of the person
            self.tries, self.hand_spot = 0, self._another_spot(w, person)
        goal = person if self.hand_spot is None else self.hand_spot
        close = np.hypot(*(person - w.pose[:2])) <= HAND_OVER if self.hand_spot is None else \
            np.hypot(*(self.hand_spot - w.pose[:2])) <= 0.15
        if close:
            offset = (0.0, 35.0, -35.0, 60.0, -60.0)[(self.tries // 3) % 5]
            wheels, facing = self._face(w, person, offset)
            self.tries += facing
            return self._out(wheels, stop=facing)
        return self._out(self._follow(w, goal, slow=0.3))

    def _another_spot(self, w, person) -> np.ndarray | None:
        """A navigable place 0.6-0.9 m from the person not tried before, the nearest (geodesic) first."""
        g = w.grid
        rc = g.cell_of(person)[0]
        k = int(np.ceil(0.9 / g.config.cell)) + 1
        rr, cc = np.mgrid[rc[0] - k:rc[0] + k + 1, rc[1] - k:rc[1] + k + 1]
        xy = g.center_of(np.c_[rr.ravel(), cc.ravel()])
        d = np.hypot(*(xy - person).T)
        xy = xy[(d >= 0.6) & (d <= 0.9)]
        xy = xy[g.is_navigable(xy)]
        for t in self.tried:
            xy = xy[np.hypot(*(xy - t).T) > 0.4]
        if not len(xy):
            return None
        geo = g.geodesic_from_field(g.distance_field(w.pose[:2]), xy)
        spot = xy[int(np.argmin(geo))]
        self.tried.append(spot)
        return spot
