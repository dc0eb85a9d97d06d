"""Speaker-following agents.

* ``oracle`` (privileged: ``env.privileged()["person"]`` and ``["world"]``): drives the geodesic shortest path to
  the person and holds 1.5 m while they walk; once they have stopped, closes to 0.7 m and stops.
* ``scripted`` (the robot's own sensors: binaural audio, depth, odometry pose, bump): a belief over where the person
  is, on a 0.1 m grid of the robot's odometry frame, starting near the robot (the task starts the two 1.2-2.2 m
  apart). Every step the belief spreads as far as a person walks (1.4 m/s, a Gaussian); every heard step multiplies
  it by the likelihood of each place given the GCC-PHAT interaural cross-correlation: the delay each place would
  cause (lateral angle, shrunk by the mouth's elevation above the microphones). One bearing is ambiguous (front or
  back, and any distance); as the robot turns and moves, the bearings from different poses intersect: the head-turn
  cue (Wallach) and triangulation in one rule. Through silences the belief only spreads: the memory of where the
  voice was last heard. Depth builds an occupancy map (people do not stand in what is solid; the planner, Dijkstra
  on the map, finds the way round); the robot turns on the spot until the belief's mass beyond 1 m is concentrated
  in one direction, then drives that way, as far as the voice's level says (inverse square against the level heard
  at the start), keeping 1.4 m, closing to 0.8 m and stopping when the level has stayed put for 3 s. Its bearings
  use onsets only (GCC-PHAT weighted by how much each 20 ms frame's energy rose: the precedence effect), because in
  these reverberant homes a whole block's cross-correlation mostly points at reflections.
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
    """Follows the voice from the robot's own sensors: a grid belief over where the person is (odometry frame),
    predicted by a walker's diffusion and updated with the GCC-PHAT interaural cross-correlation of every heard
    step (see the module's docstring)."""

    name = "scripted"
    CELL = 0.1
    SIZE = 240  # cells: 24 m x 24 m around the start
    ITD_MAX = 0.00066  # s: the KEMAR head's largest interaural delay
    MOUTH_ABOVE_EARS = 1.03  # m: a standing person's mouth above the robot's microphones
    SHARPNESS = 4.0  # likelihood exp(SHARPNESS * (normalised GCC - 1)) per heard step
    WALK = 1.4  # m/s: the fastest a person walks (the belief's diffusion while the voice is heard or not)
    FOLLOW = 1.4
    CLOSE = 0.8

    def reset(self, env, obs, info):
        super().reset(env, obs, info)
        self.sr = env.cfg.sample_rate
        self.occ = np.zeros((self.SIZE, self.SIZE), np.int16)
        self._fx = (env.cfg.width / 2) / math.tan(math.radians(env.cfg.hfov) / 2)
        c = (np.arange(self.SIZE) - self.SIZE // 2 + 0.5) * self.CELL
        self.cx, self.cy = np.meshgrid(c, c, indexing="ij")  # cell centres, [ix, iy]
        r = np.hypot(self.cx, self.cy)
        # the prior: the person calls the robot from nearby (the task starts 1.2-2.2 m apart)
        self.belief = np.where((r > 0.8) & (r < 3.0), 1.0, 1e-3)
        self.belief /= self.belief.sum()
        self.noise = None
        self.tail = np.zeros((2, 480))
        self.heard = 0
        self.est_hist: deque = deque(maxlen=int(3.0 / self.dt))
        self.levels: deque = deque(maxlen=12)
        self.level0 = None
        self.path, self.k, self.plan_at = None, 0, 0
        self.since_heard = 0.0

    def _pose(self, obs):
        x, y, s, c = (float(v) for v in obs["pose"])
        return np.array([x, y]), math.degrees(math.atan2(s, c))

    def _cell(self, xy):
        return np.floor(np.asarray(xy) / self.CELL).astype(int) + self.SIZE // 2

    # --- the belief -------------------------------------------------------------------------------------------
    def _predict(self):
        from scipy.ndimage import gaussian_filter

        sigma = self.WALK * self.dt / self.CELL
        self.belief = gaussian_filter(self.belief, sigma, mode="constant", truncate=3.0)
        self.belief[self.occ >= 3] *= 0.2  # people do not stand inside what the camera saw as solid
        self.belief += 1e-9
        self.belief /= self.belief.sum()

    def _update(self, cc: np.ndarray, weight: float, p, yaw: float):
        lag = (len(cc) - 1) // 2
        ccn = (cc - cc.min()) / max(float(np.ptp(cc)), 1e-12)
        dx, dy = self.cx - p[0], self.cy - p[1]
        d = np.hypot(dx, dy) + 1e-6
        az = np.arctan2(dy, dx) - math.radians(yaw)
        cos_el = d / np.hypot(d, self.MOUTH_ABOVE_EARS)
        expected = self.ITD_MAX * np.sin(az) * cos_el * self.sr + lag  # fractional index into cc
        lik = np.interp(expected.ravel(), np.arange(len(cc)), ccn).reshape(expected.shape)
        self.belief *= np.exp(self.SHARPNESS * min(weight, 2.0) * (lik - 1.0))
        self.belief[d < 0.45] *= 0.5  # nobody stands on the robot
        self.belief /= self.belief.sum()

    # --- acting -----------------------------------------------------------------------------------------------
    def _plan(self, p, goal):
        from scipy.ndimage import binary_dilation

        blocked = binary_dilation(self.occ >= 2, iterations=2)
        s, g = self._cell(p), np.clip(self._cell(goal), 0, self.SIZE - 1)
        blocked[s[0], s[1]] = False
        blocked[g[0], g[1]] = False
        path = _grid_path(blocked, tuple(s), tuple(g))
        self.path = np.array([goal]) if path is None else (np.array(path, float) - self.SIZE // 2 + 0.5) * self.CELL
        self.k = min(2, len(self.path) - 1)

    def act(self, obs, info):
        from agents.scripted import map_depth, onset_gcc_phat

        p, yaw = self._pose(obs)
        if "depth" in obs:
            map_depth(self.occ, obs["depth"][..., 0], p, yaw, self._fx, self.robot.camera_height, self.CELL)
        audio = obs["audio"]
        cc, weight = onset_gcc_phat(audio, self.tail, self.sr, self.ITD_MAX)
        self.tail = audio[:, -self.tail.shape[1]:].astype(np.float64)
        energy = float(np.mean(audio.astype(np.float64) ** 2))
        self.noise = energy if self.noise is None else min(self.noise * 1.02 + 1e-12, max(energy, 1e-12))
        audible = energy > max(1e-8, 30.0 * self.noise)
        self._predict()
        if audible and weight > 0:
            self._update(cc, weight, p, yaw)
            self.heard += 1
            self.since_heard = 0.0
        else:
            self.since_heard += self.dt
        if audible:
            self.levels.append(energy)
            if self.level0 is None and len(self.levels) >= 5:
                self.level0 = float(np.median(self.levels))
        bearing, conc = self._bearing(p)
        if self.heard < 3 or conc < 0.3:  # not sure yet: turn on the spot (turning tells front from back)
            return self._out(_wheels(0.0, math.radians(90.0), self.robot))
        # how far: the voice's level against the level heard at the start (1.2-2.2 m away), inverse square
        dist = 2.0
        if self.level0 is not None and self.levels:
            lvl = float(np.median(list(self.levels)[-6:]))
            dist = float(np.clip(1.7 * math.sqrt(self.level0 / max(lvl, 1e-12)), 0.5, 6.0))
        self.est_hist.append(dist)
        quiet_long = self.since_heard > 1.5
        still = len(self.est_hist) == self.est_hist.maxlen and np.ptp(np.array(self.est_hist)) < 0.5
        want = self.CLOSE if still else self.FOLLOW
        err = (bearing - yaw + 180.0) % 360.0 - 180.0
        if dist <= want and not quiet_long:
            if abs(err) < 30.0:
                return self._out([0.0, 0.0])
            return self._out(_wheels(0.0, math.copysign(math.radians(90.0), err), self.robot))
        goal = p + max(dist - want, 0.5) * np.array([math.cos(math.radians(bearing)), math.sin(math.radians(bearing))])
        self.plan_at -= 1
        if self.path is None or self.plan_at <= 0 or (obs.get("bump") is not None and obs["bump"][0] > 0):
            self._plan(p, goal)
            self.plan_at = 5
        while self.k < len(self.path) - 1 and np.linalg.norm(self.path[self.k] - p) < 0.2:
            self.k += 1
        return self._out(_pursue(p, yaw, self.path[self.k], self.robot, self.dt))

    def _bearing(self, p) -> tuple[float, float]:
        """(the world bearing of the belief's mass beyond 1 m, degrees; its concentration, the mean resultant
        length of that mass's bearings, 0-1)."""
        dx, dy = self.cx - p[0], self.cy - p[1]
        far = dx * dx + dy * dy > 1.0
        w = self.belief * far
        ang = np.arctan2(dy, dx)
        c, s = float((w * np.cos(ang)).sum()), float((w * np.sin(ang)).sum())
        tot = float(w.sum()) + 1e-12
        return math.degrees(math.atan2(s, c)), math.hypot(c, s) / tot
