"""Speaker-following agents.

* ``oracle`` (privileged: ``env.privileged()["person"]`` and ``["world"]``): drives the geodesic shortest path to
  the person and holds 1.5 m while they walk; once they have stopped, closes to 0.7 m and stops.
* ``scripted`` (the robot's own sensors: binaural audio, depth, odometry pose, bump): GCC-PHAT interaural delay ->
  lateral angle; front and back told apart by turning the head (a source in front moves against the turn, one behind
  moves with it: the Wallach cue); distance from the voice's level against the level heard at the start (the person
  starts next to the robot), bounded by the depth the camera reads in the voice's direction; the person's estimated
  positions kept as a trail of breadcrumbs (the way they went, through the doors they used); a depth occupancy
  map and a planner (Dijkstra on the map) to the newest breadcrumb; memory of where the voice was last heard through
  silences; standing off 1.4 m while the voice moves, closing to 0.8 m when it has stayed in one place.
* ``random``: uniform wheel velocities (:class:`agents.scripted.RandomAgent`).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from agents.scripted import Agent, _grid_path, _pursue, _wheels


class OracleFollower(Agent):
    name = "oracle"
    FOLLOW = 1.5  # m held while the person walks
    CLOSE = 0.7  # m once they have stopped

    def reset(self, env, obs, info):
        super().reset(env, obs, info)
        self.path, self.k, self.plan_at = None, 0, -1

    def act(self, obs, info):
        priv = self.env.privileged()
        w, person, d = priv["world"], priv["person"], priv["distance"]
        p, yaw = w.pose[:2], w.pose[2]
        want = self.CLOSE if person.finished else self.FOLLOW
        spot = None if person.finished or not (person.walking or d < 1.5) else self._yield_spot(w, person)
        if spot is not None:  # the person is coming back this way: step out of their path
            return self._out(_pursue(p, yaw, spot, self.robot, self.dt, slow_within=0.3))
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
        while (self.k < len(self.path) - 1 and np.linalg.norm(self.path[self.k] - p) < 0.2
               and w.grid.line_of_sight(p, self.path[self.k + 1])):
            self.k += 1
        return self._out(_pursue(p, yaw, self.path[self.k], self.robot, self.dt))


    def _yield_spot(self, w, person) -> np.ndarray | None:
        """Where to stand when the person's next 3 m pass within 0.8 m of the robot: the nearest free place
        (within 1.5 m) at least 1 m from that stretch and 1-2.5 m from the person; None when not in the way."""
        ahead = person.upcoming(3.0)
        p = w.pose[:2]
        if len(ahead) < 2 or np.min(np.linalg.norm(ahead[1:] - p, axis=1)) >= 0.8:
            return None
        g = w.grid
        rc = g.cell_of(p)[0]
        r = int(math.ceil(1.5 / g.config.cell))
        rows, cols = np.mgrid[max(rc[0] - r, 0):min(rc[0] + r + 1, g.shape[0]),
                              max(rc[1] - r, 0):min(rc[1] + r + 1, g.shape[1])]
        cells = np.stack([rows.ravel(), cols.ravel()], 1)
        cells = cells[g.labels[cells[:, 0], cells[:, 1]] == g.main_label]
        if len(cells) == 0:
            return None
        xy = g.center_of(cells)
        far = np.min(np.linalg.norm(xy[:, None] - ahead[None, 1:], axis=2), axis=1)
        dp = np.linalg.norm(xy - person.pos, axis=1)
        ok = (far >= 1.0) & (dp >= 1.0) & (dp <= 2.5) & (np.linalg.norm(xy - p, axis=1) <= 1.5)
        if not np.any(ok):
            return None
        cand = xy[ok]
        return cand[int(np.argmin(np.linalg.norm(cand - p, axis=1)))]


class ScriptedFollower(Agent):
    """Follows the voice from the robot's own sensors (see the module's docstring)."""

    name = "scripted"
    CELL = 0.1
    SIZE = 300  # cells: 30 m x 30 m around the start
    ITD_MAX = 0.00066
    FOLLOW = 1.4
    CLOSE = 0.8

    def reset(self, env, obs, info):
        super().reset(env, obs, info)
        self.sr = env.cfg.sample_rate
        self.occ = np.zeros((self.SIZE, self.SIZE), np.int16)
        self._fx = (env.cfg.width / 2) / math.tan(math.radians(env.cfg.hfov) / 2)
        self.level0 = None  # the voice's level at the start (about 1.7 m away)
        self.levels: deque = deque(maxlen=8)
        self.crumbs: list[np.ndarray] = []
        self.target = None
        self.since_heard = 1e9
        self.still_for = 0.0
        self.facing_known = False
        self.test_left, self.test_lats, self.turn_round = 0, [], 0
        self.path, self.k, self.plan_at = None, 0, 0
        self.t = 0.0
        self.noise = None

    # --- perception -------------------------------------------------------------------------------------------
    def _pose(self, obs):
        x, y, s, c = (float(v) for v in obs["pose"])
        return np.array([x, y]), math.degrees(math.atan2(s, c))

    def _itd(self, audio):
        from agents.scripted import GanAgent

        return GanAgent._itd(self, audio)

    def _depth_at(self, obs, bearing_rel: float) -> float | None:
        """Depth (m) in the direction ``bearing_rel`` (deg, left positive) at heights of 0.9-1.6 m, or None."""
        if "depth" not in obs:
            return None
        d = obs["depth"][..., 0]
        H, W = d.shape
        u = -math.tan(math.radians(bearing_rel)) * self._fx + W / 2
        if abs(bearing_rel) > 40 or not (2 <= u < W - 2):
            return None
        col = d[:, int(u) - 2:int(u) + 3]
        rows = np.arange(H)[:, None]
        v = (rows - H / 2 + 0.5) / self._fx
        h = self.robot.camera_height - v * col
        ok = (col > 0.1) & (h > 0.9) & (h < 1.6)
        return float(np.median(col[ok])) if np.count_nonzero(ok) >= 3 else None

    def _map_depth(self, obs, p, yaw):
        from agents.scripted import GanAgent

        GanAgent._map_depth(self, obs, p, yaw)

    def _cell(self, xy):
        return np.floor(np.asarray(xy) / self.CELL).astype(int) + self.SIZE // 2

    def _plan(self, p, goal):
        from scipy.ndimage import binary_dilation

        blocked = binary_dilation(self.occ >= 2, iterations=2)
        s, g = self._cell(p), np.clip(self._cell(goal), 0, self.SIZE - 1)
        blocked[s[0], s[1]] = False
        blocked[g[0], g[1]] = False
        path = _grid_path(blocked, tuple(s), tuple(g))
        self.path = np.array([goal]) if path is None else (np.array(path, float) - self.SIZE // 2 + 0.5) * self.CELL
        self.k = min(2, len(self.path) - 1)

    # --- acting -----------------------------------------------------------------------------------------------
    def _turn(self, deg_s: float):
        return self._out(_wheels(0.0, math.radians(max(-120.0, min(120.0, deg_s))), self.robot))

    def act(self, obs, info):
        self.t += self.dt
        p, yaw = self._pose(obs)
        self._map_depth(obs, p, yaw)
        itd, energy = self._itd(obs["audio"])
        self.noise = energy if self.noise is None else min(self.noise * 1.02 + 1e-12, max(energy, 1e-12))
        audible = energy > max(1e-8, 30.0 * self.noise)
        if not audible:
            self.since_heard += self.dt
            if self.since_heard > 2.0:
                self.facing_known = False  # the voice may come from anywhere when it comes back
        else:
            self.since_heard = 0.0
            lat = math.degrees(math.asin(max(-1.0, min(1.0, itd / self.ITD_MAX))))
            self.levels.append(energy)
            if self.level0 is None and len(self.levels) >= 5:
                self.level0 = float(np.median(self.levels))
            if self.test_left > 0:  # a test turn to the left: a source in front drifts right (lat falls)
                self.test_lats.append(lat)
                self.test_left -= 1
                if self.test_left == 0:
                    drift = self.test_lats[-1] - self.test_lats[0]
                    self.facing_known = True
                    if drift > 0:  # it drifted left: it is behind; turn round towards it
                        self.turn_round = int(math.ceil(140.0 / (120.0 * self.dt)))
                return self._turn(100.0)
            if self.turn_round > 0:
                self.turn_round -= 1
                return self._turn(math.copysign(120.0, lat if abs(lat) > 5 else 1.0))
            if abs(lat) > 12.0:  # turn towards the voice: turning towards the leading ear always ends facing it
                self.facing_known = True
                return self._turn(math.copysign(min(120.0, 2.0 * abs(lat) / self.dt * 0.1 + 30.0), lat))
            if not self.facing_known:  # straight ahead or straight behind: find out with a test turn
                self.test_left, self.test_lats = 4, [lat]
                return self._turn(100.0)
            bearing = yaw + lat
            dist = self._distance(obs, lat)
            est = p + dist * np.array([math.cos(math.radians(bearing)), math.sin(math.radians(bearing))])
            if self.target is not None and np.linalg.norm(est - self.target) < 0.5:
                self.still_for += self.dt
            elif self.target is not None:
                self.still_for = max(0.0, self.still_for - 2 * self.dt)
            self.target = est if self.target is None else 0.6 * self.target + 0.4 * est
            if not self.crumbs or np.linalg.norm(self.target - self.crumbs[-1]) > 0.7:
                self.crumbs.append(self.target.copy())
        if self.target is None:  # nothing placed yet: turn slowly, listening
            return self._turn(60.0)
        want = self.CLOSE if self.still_for > 3.0 else self.FOLLOW
        if float(np.linalg.norm(self.target - p)) <= want:
            return self._out([0.0, 0.0])
        while len(self.crumbs) > 1 and np.linalg.norm(self.crumbs[0] - p) < 0.6:
            self.crumbs.pop(0)
        goal = self.crumbs[0] if self.crumbs else self.target
        if np.linalg.norm(self.target - goal) < want:
            goal = self.target
        self.plan_at -= 1
        if self.path is None or self.plan_at <= 0 or (obs.get("bump") is not None and obs["bump"][0] > 0):
            self._plan(p, goal)
            self.plan_at = 5
        while self.k < len(self.path) - 1 and np.linalg.norm(self.path[self.k] - p) < 0.2:
            self.k += 1
        return self._out(_pursue(p, yaw, self.path[self.k], self.robot, self.dt))

    def _distance(self, obs, az: float) -> float:
        d = 1.7
        if self.level0 is not None and len(self.levels):
            lvl = float(np.median(list(self.levels)[-4:]))
            d = 1.7 * math.sqrt(self.level0 / max(lvl, 1e-12))  # inverse square on energy
        d = float(np.clip(d, 0.5, 8.0))
        seen = self._depth_at(obs, ((az + 180.0) % 360.0) - 180.0)
        if seen is not None:
            d = min(d, seen + 0.1)
        return d
