"""Speaker-following agents.

* ``oracle`` (privileged: ``env.privileged()["person"]`` and ``["world"]``): drives the geodesic shortest path to
  the person and holds 1.5 m while they walk, stepping out of their way when their next 4 m of route pass within
  0.9 m of it (people walk back out of dead-end rooms); once they have stopped, closes to 0.7 m and stops.
* ``scripted`` (:class:`MapFollower`; the robot's own sensors and the task's semantic map: the floor plan and its
  start pose, then odometry; never the person): a belief over where the person stands on the map's floor
  (:class:`agents.retrieval.SpeakerBelief`: voice onsets heard from a place's own direction in line of sight, through
  the doorway or round the corner otherwise; a person the camera sees standing on open floor of the map; the places
  it sees empty), spread every step along the floor as far as a walker goes; it drives along the map to the person
  it sees (1.7 m behind; 0.7 m and still once they have stood for 2.5 s); a person lost from view in the last 3 s
  is looked for 1 m beyond where they were heading; otherwise it goes to 0.8 m of the belief's densest place, or
  turns on the spot listening when the belief is spread. ``mode`` says which it did ("seen", "lost-sight",
  "heard", "unsure"). Its settings were tuned on ``val`` episodes.
* ``random``: uniform wheel velocities (:class:`agents.scripted.RandomAgent`).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from agents.scripted import (Agent, MapDriver, _pursue, _wheels, draw_route, ego_offsets, next_waypoint,
                             window_cells)


class OracleFollower(Agent):
    name = "oracle"
    FOLLOW = 1.5  # m held while the person walks
    CLOSE = 0.7  # m once they have stopped

    def reset(self, env, obs, info):
        super().reset(env, obs, info)
        self.path, self.k, self.plan_at = None, 0, -1
        self._field, self._field_key = None, None  # the person's geodesic field, per cell they stand in

    def act(self, obs, info):
        priv = self.env.privileged()
        w, person, d = priv["world"], priv["person"], priv["distance"]
        p, yaw = w.pose[:2], w.pose[2]
        want = self.CLOSE if person.finished else self.FOLLOW
        spot = None if person.finished or person.escorting else self._yield_spot(w, person)
        if spot is not None:  # the person is coming back this way: step out of their path (round what is in the way)
            way, length = w.grid.shortest_path(p, spot)
            nxt = way[1] if np.isfinite(length) and len(way) > 1 else spot
            self.path = None
            return self._out(_pursue(p, yaw, nxt, self.robot, self.dt, slow_within=0.3))
        if d <= want:  # close enough: face the person and hold still
            v = person.pos - p
            err = (math.degrees(math.atan2(v[1], v[0])) - yaw + 180.0) % 360.0 - 180.0
            if person.finished or abs(err) < 20.0:
                return self._out([0.0, 0.0])
            return self._out(_wheels(0.0, math.copysign(min(abs(math.radians(err)) / self.dt * 0.8,
                                                            math.radians(self.robot.max_turn_deg)), err),
                                     self.robot))
        self.plan_at -= 1
        if self.path is None or self.plan_at <= 0 or w.bumped:
            path, length = w.grid.shortest_path(p, person.pos)
            self.path = path if np.isfinite(length) and len(path) > 1 else np.array([p, person.pos])
            self.k, self.plan_at = 1, 5
        self.k = next_waypoint(w.grid, self.path, self.k, p)
        return self._out(_pursue(p, yaw, self.path[self.k], self.robot, self.dt))


    def _yield_spot(self, w, person) -> np.ndarray | None:
        """Where to stand when the person's next 4 m pass within 0.9 m of the robot: the nearest free place
        (within 2.5 m) at least 1.1 m from that stretch and 1-2.2 m from the person along the floor; None when not
        in the way."""
        ahead = person.upcoming(4.0)
        p = w.pose[:2]
        if len(ahead) < 2 or np.min(np.linalg.norm(ahead[1:] - p, axis=1)) >= 0.9:
            return None
        g = w.grid
        rc = g.cell_of(p)[0]
        r = int(math.ceil(2.5 / g.config.cell))
        rows, cols = np.mgrid[max(rc[0] - r, 0):min(rc[0] + r + 1, g.shape[0]),
                              max(rc[1] - r, 0):min(rc[1] + r + 1, g.shape[1])]
        cells = np.stack([rows.ravel(), cols.ravel()], 1)
        cells = cells[g.labels[cells[:, 0], cells[:, 1]] == g.main_label]
        if len(cells) == 0:
            return None
        xy = g.center_of(cells)
        far = np.min(np.linalg.norm(xy[:, None] - ahead[None, 1:], axis=2), axis=1)
        key = tuple(g.cell_of(person.pos)[0])
        if self._field_key != key:
            self._field, self._field_key = g.distance_field(person.pos), key
        dp = g.geodesic_from_field(self._field, xy)  # along the floor: a spot round a corner is farther
        ok = (far >= 1.1) & (dp >= 1.0) & (dp <= 2.2) & (np.linalg.norm(xy - p, axis=1) <= 2.5)
        if not np.any(ok):
            return None
        cand = xy[ok]
        return cand[int(np.argmin(np.linalg.norm(cand - p, axis=1)))]


class MapFollower(MapDriver):
    """Follows the voice on the home's map (``env.semantic_map()``: the floor plan and its own start pose, then
    odometry; never the person). Where the person is: :class:`agents.retrieval.SpeakerBelief` (voice onsets heard
    from a place's own direction in line of sight, through the doorway or round the corner otherwise; the camera's
    person detector, which looks for what stands at chest height on open floor of the map, and the places it sees
    empty), started 1-2.5 m from the robot and spread every step along the floor as far as a person walks. It drives
    along the map to the person it sees, holding ``FOLLOW``, ``CLOSE`` and still once they have stood for 2.5 s;
    to ``LOOK_AHEAD`` beyond where a person just lost from view was heading; otherwise to the belief's densest place,
    or turns on the spot listening when the belief is spread."""

    name = "scripted"
    CELL = 0.2
    SPREAD = 0.6  # of the belief moved to the neighbouring cells per 0.1 s step (a walker's 1.4 m/s on 0.2 m cells)
    FOLLOW, CLOSE = 1.7, 0.7  # m: behind a walking person; from one who has stood for 2.5 s
    LOOK_AHEAD = 1.0  # m beyond where a person just lost from view was heading (0: trust the belief)
    HEARD = 0.8  # m: how close it goes to where it only hears the person (closer than when it sees them)

    def reset(self, env, obs, info):
        super().reset(env, obs, info)
        from scipy.sparse import diags, identity

        from agents.retrieval import SpeakerBelief, _Me

        self.map = m = env.semantic_map()
        self.me = _Me(m.grid)
        self.ears = e = SpeakerBelief(m.grid, env.cfg.sample_rate, self.CELL)
        self._fx = (env.cfg.width / 2) / math.tan(math.radians(env.cfg.hfov) / 2)
        deg = np.asarray(e.graph.getnnz(axis=1), float)
        a = (e.graph > 0).astype(float)
        self.move = (diags(1.0 / np.maximum(deg, 1.0)) @ a).T.tocsr()  # column-stochastic: one cell on
        self.stay = identity(len(e.xy), format="csr")
        _, length = e.arrivals(np.array(m.start[:2]))
        prior = np.exp(-((length - 1.7) / 0.6) ** 2) + 1e-6
        e.belief[:] = prior / prior.sum()
        self.sightings: deque = deque(maxlen=int(3.0 / self.dt))
        self.t = 0.0
        self.mode = "unsure"

    def _spread(self) -> None:
        e = self.ears
        for i in range(2):
            e.belief[i] = (1 - self.SPREAD) * e.belief[i] + self.SPREAD * (self.move @ e.belief[i])
        e._normalise()

    def act(self, obs, info):
        self.t += self.dt
        p, yaw = self.map.to_map(obs["pose"])
        self.me.pose[:] = (p[0], p[1], yaw)
        self.me.bumped = obs.get("bump") is not None and obs["bump"][0] > 0
        self._spread()
        self.ears.hear(obs["audio"], p, yaw)
        if "depth" in obs:
            seen = self.ears.see(obs["depth"][..., 0], p, yaw, self._fx, self.robot.camera_height)
            if seen is not None:
                self.sightings.append((self.t, seen))
        recent = [q for t, q in self.sightings if self.t - t <= 1.0]
        if recent:
            self.mode = "seen"
            q = recent[-1]
            lasting = [q2 for t, q2 in self.sightings if self.t - t <= 2.5]
            still = self.sightings[0][0] <= self.t - 2.4 and np.ptp(np.array(lasting), axis=0).max() < 0.35
            want = self.CLOSE if still else self.FOLLOW
        elif self.LOOK_AHEAD > 0 and self.sightings and self.t - self.sightings[-1][0] <= 3.0 and \
                len(self.sightings) >= 2 and np.hypot(*(self.sightings[-1][1] - self.sightings[0][1])) > 0.3:
            # just lost from view (a door, a corner): where they were heading
            v = self.sightings[-1][1] - self.sightings[0][1]
            q = self.sightings[-1][1] + self.LOOK_AHEAD * v / np.hypot(*v)
            self.mode, want = "lost-sight", 0.3
        else:
            q, mass = self.ears.best(0)
            if mass < 0.05:
                self.mode = "unsure"  # turn on the spot, listening and looking
                return self._out(_wheels(0.0, math.radians(90.0), self.robot))
            self.mode, want = "heard", self.HEARD
        d = self._distance(p, q)
        if d <= want:
            v = q - p
            err = (math.degrees(math.atan2(v[1], v[0])) - yaw + 180.0) % 360.0 - 180.0
            if self.mode == "seen" and want == self.CLOSE or abs(err) < 20.0:
                return self._out([0.0, 0.0])
            return self._out(_wheels(0.0, math.copysign(min(math.radians(90.0), abs(math.radians(err)) / self.dt),
                                                        err), self.robot))
        goal = self.ears.snap(q)
        if self.goal is not None and np.hypot(*(self.goal - goal)) < 0.3:
            goal = self.goal  # no re-planning for small moves
        return self._out(self._follow(self.me, goal, slow=0.3))

    def _distance(self, p, q) -> float:
        """Along the floor (the belief's cells), from ``p`` to ``q``."""
        _, length = self.ears.arrivals(p)
        i = int(np.argmin(np.sum((self.ears.xy - q) ** 2, axis=1)))
        return float(length[i])


class EgoMap(MapFollower):
    """What a learned follower reads of the map (``--map`` on ``sonicverse train``; ``AVNavConfig.map_shape``): the
    scripted follower's perception, run on the robot's own sensors and its semantic map as :class:`MapFollower`
    runs it, drawn as an egocentric image of ``SIZE`` x ``SIZE`` pixels of ``RES`` m, the robot at the centre facing
    the top (its left to the left), uint8 channels:

    0. the floor plan's navigable floor;
    1. the belief over where the person stands (audio and vision), the likeliest place at 255;
    2. the person the camera saw in the last 3 s, fading with age;
    3. the route the scripted follower would drive now (empty when it would turn or stand).

    The policy decides what to do with them: it is trained on the oracle's actions, not on the scripted
    follower's."""

    SIZE, RES = 32, 0.25
    CHANNELS = 4
    SEEN_S = 3.0

    def reset(self, env, obs, info):
        super().reset(env, obs, info)
        g, e = self.map.grid, self.ears
        self._k = max(1, int(round(self.CELL / g.config.cell)))
        self._bel = np.zeros((-(-g.shape[0] // self._k), -(-g.shape[1] // self._k)))
        self._bi = e.cells // self._k
        self._floor = (g.labels == g.main_label)
        self._fwd, self._left = ego_offsets(self.SIZE, self.RES)
        self._routed = False
        self.image = np.zeros((self.CHANNELS, self.SIZE, self.SIZE), np.uint8)

    def _follow(self, w, goal, slow: float = 0.0):
        self._routed = True
        return super()._follow(w, goal, slow)

    def observe(self, obs, info) -> np.ndarray:
        """Run the scripted follower's step on ``obs`` (its action is kept in ``self.action``, not taken) and return
        the image (C, H, W) uint8 (the same array each step: copy it to keep it)."""
        self._routed = False
        self.action = self.act(obs, info)  # the scripted follower's (``train --teacher scripted``'s labels)
        p, yaw = self.me.pose[:2], self.me.pose[2]
        x, y, r, c, inside = window_cells(self.map.grid, p[0], p[1], yaw, self._fwd, self._left)
        img = self.image
        img[0] = (self._floor[r, c] & inside).reshape(self.SIZE, self.SIZE) * np.uint8(255)
        b = self.ears.belief[0]
        self._bel.fill(0.0)
        self._bel[self._bi[:, 0], self._bi[:, 1]] = b / max(float(b.max()), 1e-12)
        img[1] = np.round(255 * self._bel[r // self._k, c // self._k] * inside).reshape(self.SIZE, self.SIZE)
        seen = np.zeros(x.shape)
        for t, q in self.sightings:
            age = self.t - t
            if age <= self.SEEN_S:
                near = (x - q[0]) ** 2 + (y - q[1]) ** 2 <= (0.3 ** 2)
                seen = np.where(near, np.maximum(seen, 1.0 - age / self.SEEN_S), seen)
        img[2] = np.round(255 * seen)
        img[3] = 0
        if self._routed and self.path is not None:
            draw_route(img[3], p, yaw, np.vstack([p[None], self.path[min(self.k, len(self.path) - 1):]]), self.RES)
        return img


def floor_safe(table: np.ndarray, grid, pose, robot, horizon_s: float) -> np.ndarray:
    """Which rows of ``table`` (normalised wheel velocities, left and right, one row per discrete action) keep the
    robot on ``grid``'s navigable floor when held for ``horizon_s`` seconds from ``pose`` (x, y, yaw degrees on the
    grid's frame), integrated as the world integrates a step (:func:`sonicverse_core.world.robot.integrate`, whose
    rotation is never blocked). ``grid`` is what the robot may know (the task's floor plan); a person is not on it."""
    from sonicverse_core.world.robot import integrate

    nav = grid.navigable
    c, ox, oy = grid.config.cell, float(grid.origin[0]), float(grid.origin[1])
    rows, cols = nav.shape

    def free(x: float, y: float) -> bool:
        col, row = math.floor((x - ox) / c), math.floor((y - oy) / c)
        return 0 <= row < rows and 0 <= col < cols and bool(nav[row, col])

    p = np.asarray(pose, float)
    ok = np.ones(len(table), bool)
    for i, wheels in enumerate(np.asarray(table, float)[:, :2]):
        if wheels[0] + wheels[1] > 0:  # only moving forward can bump (no row drives backwards)
            ok[i] = not integrate(robot, p, wheels, horizon_s, free)[1]
    return ok
