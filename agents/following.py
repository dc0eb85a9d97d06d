"""Speaker-following agents.

* ``oracle`` (privileged: ``env.privileged()["person"]`` and ``["world"]``): drives the geodesic shortest path to
  the person and holds 1.5 m while they walk, stepping out of their way when their next 4 m of route pass within
  0.9 m of it (people walk back out of dead-end rooms); once they have stopped, closes to 0.7 m and stops.
* ``scripted`` (the robot's own sensors: binaural audio, depth, odometry pose, bump): two beliefs over where the
  person is, on a 0.1 m grid of the robot's odometry frame, both starting near the robot (the task starts the two
  1.2-2.2 m apart). Every step they spread as far as a person walks (1.4 m/s, a Gaussian); every heard step
  multiplies them by the likelihood of each place given the interaural cross-correlation (GCC-PHAT weighted towards
  onsets: the precedence effect; in these reverberant homes a whole block's cross-correlation mostly points at
  reflections), i.e. the delay each place would cause (its lateral angle, shrunk by the mouth's elevation above the
  microphones). One bearing is ambiguous (front or back, any distance); as the robot turns and moves, bearings from
  different poses intersect: the head-turn cue (Wallach) and triangulation in one rule. The camera adds what it sees:
  a narrow thing at chest and head height standing in front of its surroundings (:func:`detect_people`), accepted
  only where the audio-only belief may put the voice, is fused into the acting belief and followed directly (1.4 m,
  closing to 0.7 m and stopping once it has stayed put for 3 s). Otherwise the robot drives towards the bearing of
  the acting belief's mass beyond 1 m, at least 1.5 m or as far as the voice's level says (inverse square against
  the level at the start; only the camera makes it stop: in a reverberant home the level says little about
  distance); when that mass is spread it goes where the voice was last placed (memory through silences, 8 s) or
  turns on the spot listening. Depth and bumps build an occupancy map; a planner (Dijkstra on it) finds the way round.
  A person just lost from view (a door, a corner) is looked for 1 m beyond where they were last seen, along their
  motion. ``mode`` says which of these it did last ("seen", "lost-sight", "heard", "memory", "unsure").
* ``random``: uniform wheel velocities (:class:`agents.scripted.RandomAgent`).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from agents.scripted import Agent, MapAgent, _pursue, _wheels


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
        while (self.k < len(self.path) - 1 and np.linalg.norm(self.path[self.k] - p) < 0.2
               and w.grid.line_of_sight(p, self.path[self.k + 1])):
            self.k += 1
        return self._out(_pursue(p, yaw, self.path[self.k], self.robot, self.dt))


    def _yield_spot(self, w, person) -> np.ndarray | None:
        """Where to stand when the person's next 4 m pass within 0.9 m of the robot: the nearest free place
        (within 2.5 m) at least 1.1 m from that stretch and 1-2.2 m from the person; None when not in the way."""
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
        dp = np.linalg.norm(xy - person.pos, axis=1)
        ok = (far >= 1.1) & (dp >= 1.0) & (dp <= 2.2) & (np.linalg.norm(xy - p, axis=1) <= 2.5)
        if not np.any(ok):
            return None
        cand = xy[ok]
        return cand[int(np.argmin(np.linalg.norm(cand - p, axis=1)))]


def detect_people(depth: np.ndarray, fx: float, camera_height: float, band=(1.0, 1.65), jump: float = 0.4,
                  width=(0.2, 0.75)) -> list[tuple[float, float]]:
    """People in a depth image: narrow things at chest and head height (``band``, m above the floor) that stand
    ``jump`` m or more in front of what is beside them on both sides, ``width`` m wide. Returns [(bearing degrees,
    left positive, distance m)]. Walls, tables and sofas fail the test (too wide, or too low); a door's edge or a
    shelf seen end-on can pass it, which is why the follower gates detections by the voice's direction."""
    H, W = depth.shape
    v = (np.arange(H)[:, None] - H / 2 + 0.5) / fx
    h = camera_height - v * depth
    inband = (depth > 0.1) & (h >= band[0]) & (h <= band[1])
    col = np.where(inband, depth, np.inf).min(axis=0)  # nearest thing at that height, per column
    valid = np.isfinite(col)
    out = []
    u = 0
    while u < W:
        if not valid[u]:
            u += 1
            continue
        a = u
        while u + 1 < W and valid[u + 1] and abs(col[u + 1] - col[u]) < 0.15:
            u += 1
        b = u
        z = float(np.median(col[a:b + 1]))
        left = col[a - 1] if a > 0 else np.inf
        right = col[b + 1] if b + 1 < W else np.inf
        metres = (b - a + 1) * z / fx
        if a > 0 and b + 1 < W and left - z >= jump and right - z >= jump and width[0] <= metres <= width[1]:
            uc = (a + b + 1) / 2
            ang = math.degrees(math.atan(-(uc - W / 2) / fx))
            out.append((ang, z / math.cos(math.radians(ang))))
        u = b + 1
    return out


class ScriptedFollower(MapAgent):
    """Follows the voice (and what the camera sees where the voice is) from the robot's own sensors; see the
    module's docstring."""

    name = "scripted"
    ITD_MAX = 0.00066  # s: the KEMAR head's largest interaural delay
    MOUTH_ABOVE_EARS = 1.03  # m: a standing person's mouth above the robot's microphones
    SHARPNESS = 4.0  # likelihood exp(SHARPNESS * (normalised GCC - 1)) per heard step
    WALK = 1.4  # m/s: the fastest a person walks (the belief's diffusion while the voice is heard or not)
    FOLLOW = 1.4
    CLOSE = 0.7

    def reset(self, env, obs, info):
        super().reset(env, obs, info)
        self.sr = env.cfg.sample_rate
        self.occ = np.zeros((self.SIZE, self.SIZE), np.int16)
        self._fx = (env.cfg.width / 2) / math.tan(math.radians(env.cfg.hfov) / 2)
        c = (np.arange(self.SIZE) - self.SIZE // 2 + 0.5) * self.CELL
        self.cx, self.cy = np.meshgrid(c, c, indexing="ij")  # cell centres, [ix, iy]
        r = np.hypot(self.cx, self.cy)
        # the prior: the person calls the robot from nearby (the task starts 1.2-2.2 m apart)
        prior = np.where((r > 0.8) & (r < 3.0), 1.0, 1e-3)
        # two beliefs: [0] from audio and vision (what the robot acts on), [1] from audio alone (what judges
        # whether a thing the camera sees is the talker: vision must not confirm itself)
        self.belief = np.stack([prior, prior]) / prior.sum()
        self.noise = None
        self.tail = np.zeros((2, 480))
        self.heard = 0
        self.levels: deque = deque(maxlen=12)
        self.level0 = None
        self.last_seen = None
        self.memory, self.memory_t = None, -1e9
        self.sightings: deque = deque(maxlen=int(5.0 / self.dt))
        self.t = 0.0
        self.path, self.k, self.plan_at = None, 0, 0
        self.since_heard = 0.0

    # --- the belief -------------------------------------------------------------------------------------------
    def _predict(self):
        from scipy.ndimage import gaussian_filter

        sigma = self.WALK * self.dt / self.CELL
        self.belief = gaussian_filter(self.belief, (0, sigma, sigma), mode="constant", truncate=3.0)
        self.belief[:, self.occ >= 3] *= 0.2  # people do not stand inside what the camera saw as solid
        self.belief += 1e-9
        self.belief /= self.belief.sum(axis=(1, 2), keepdims=True)

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
        self.belief[:, d < 0.45] *= 0.5  # nobody stands on the robot
        self.belief /= self.belief.sum(axis=(1, 2), keepdims=True)

    # --- acting -----------------------------------------------------------------------------------------------
    def act(self, obs, info):
        from agents.scripted import map_depth, onset_gcc_phat

        self.t += self.dt
        p, yaw = self._pose(obs)
        if "depth" in obs:
            map_depth(self.occ, obs["depth"][..., 0], p, yaw, self._fx, self.robot.camera_height, self.CELL)
        self.bumped = obs.get("bump") is not None and obs["bump"][0] > 0
        if self.bumped:  # something the camera missed is in front: put it on the map
            for da in (-30.0, 0.0, 30.0):
                a = math.radians(yaw + da)
                q = p + (self.robot.radius + 0.08) * np.array([math.cos(a), math.sin(a)])
                c = self._cell(q)
                if np.all((c >= 0) & (c < self.SIZE)):
                    self.occ[c[0], c[1]] += 3
            self.path = None
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
        seen = self._see(obs, p, yaw) if "depth" in obs else None
        if seen is not None:
            self.mode = "seen"
            self.sightings.append((self.t, seen))
            return self._follow_seen(seen, p, yaw)
        lost = self._where_lost()
        if lost is not None and np.linalg.norm(lost - p) > 0.4:
            self.mode = "lost-sight"  # just lost from view (a door, a corner): go where they were heading
            return self._go(p, yaw, lost)
        if audible:
            self.levels.append(energy)
            if self.level0 is None and len(self.levels) >= 5:
                self.level0 = float(np.median(self.levels))
        bearing, conc = self._bearing(p)
        dist = 2.0  # how far: the voice's level against the level heard at the start (1.2-2.2 m), inverse square
        if self.level0 is not None and self.levels:
            lvl = float(np.median(list(self.levels)[-6:]))
            dist = float(np.clip(1.7 * math.sqrt(self.level0 / max(lvl, 1e-12)), 0.5, 6.0))
        if self.heard >= 3 and conc >= 0.25:
            self.memory = p + dist * np.array([math.cos(math.radians(bearing)), math.sin(math.radians(bearing))])
            self.memory_t = self.t
        elif self.memory is not None and self.t - self.memory_t < 8.0 and np.linalg.norm(self.memory - p) > 0.5:
            self.mode = "memory"  # unsure now: go where the voice was last placed
            return self._go(p, yaw, self.memory)
        else:
            self.mode = "unsure"  # turn on the spot, listening (turning tells front from back)
            return self._out(_wheels(0.0, math.radians(90.0), self.robot))
        self.mode = "heard"  # the level says little about distance in a reverberant home: only the camera stops it
        err = (bearing - yaw + 180.0) % 360.0 - 180.0
        if abs(err) > 60.0:
            return self._out(_wheels(0.0, math.copysign(math.radians(90.0), err), self.robot))
        goal = p + max(dist, 1.5) * np.array([math.cos(math.radians(bearing)), math.sin(math.radians(bearing))])
        return self._go(p, yaw, goal)

    def _go(self, p, yaw, goal):
        self.plan_at -= 1
        if self.path is None or self.plan_at <= 0 or self.bumped:
            self._plan_to(p, goal)
            self.plan_at = 4
        while self.k < len(self.path) - 1 and np.linalg.norm(self.path[self.k] - p) < 0.2:
            self.k += 1
        return self._out(_pursue(p, yaw, self.path[self.k], self.robot, self.dt))

    def _see(self, obs, p, yaw) -> np.ndarray | None:
        """A person the camera sees where the voice is (where the audio-only belief holds at least 30% of its
        largest mass within ~0.7 m; 10% within 1 m of the last sighting); fused into the acting belief; their
        position or None."""
        people = detect_people(obs["depth"][..., 0], self._fx, self.robot.camera_height)
        if not people:
            return None
        from scipy.ndimage import uniform_filter

        audio = uniform_filter(self.belief[1], size=15, mode="constant")  # audio-only mass within ~0.7 m
        top = float(audio.max())
        best, score = None, -1.0
        for ang, dist in people:
            b = yaw + ang
            pos = p + (dist + 0.15) * np.array([math.cos(math.radians(b)), math.sin(math.radians(b))])  # body centre
            c = np.clip(self._cell(pos), 0, self.SIZE - 1)
            support = float(audio[c[0], c[1]]) / max(top, 1e-30)
            near_last = self.last_seen is not None and np.linalg.norm(pos - self.last_seen[0]) < 1.0 \
                and self.t - self.last_seen[1] < 2.0 and support >= 0.1
            if (support >= 0.3 or near_last) and support > score:
                best, score = pos, support
        if best is None:
            return None
        g = np.exp(-((self.cx - best[0]) ** 2 + (self.cy - best[1]) ** 2) / (2 * 0.3 ** 2))
        self.belief[0] *= 0.05 + g
        self.belief[0] /= self.belief[0].sum()
        self.last_seen = (best, self.t)
        return best

    def _where_lost(self) -> np.ndarray | None:
        """Where a person seen in the last 4 s went: the last sighting, 1 m further along their recent motion."""
        if not self.sightings or self.t - self.sightings[-1][0] > 4.0:
            return None
        t1, q1 = self.sightings[-1]
        old = [q for t, q in self.sightings if t1 - t >= 0.8]
        if not old:
            return q1
        v = q1 - old[-1]
        n = float(np.hypot(*v))
        return q1 + (v / n if n > 0.2 else 0.0)

    def _follow_seen(self, person, p, yaw):
        recent = [q for t, q in self.sightings if self.t - t <= 3.0]
        still = len(recent) >= int(1.5 / self.dt) and np.ptp(np.array(recent), axis=0).max() < 0.35
        want = self.CLOSE if still else self.FOLLOW
        to = person - p
        dist = float(np.hypot(*to))
        err = (math.degrees(math.atan2(to[1], to[0])) - yaw + 180.0) % 360.0 - 180.0
        if dist <= want:
            if abs(err) < 20.0 or (still and dist <= self.CLOSE):
                return self._out([0.0, 0.0])
            return self._out(_wheels(0.0, math.copysign(min(math.radians(90.0), abs(math.radians(err)) / self.dt),
                                                        err), self.robot))
        return self._go(p, yaw, p + to * (dist - want) / dist)

    def _bearing(self, p, which: int = 0) -> tuple[float, float]:
        """(the world bearing of the belief's mass beyond 1 m, degrees; its concentration, the mean resultant
        length of that mass's bearings, 0-1)."""
        dx, dy = self.cx - p[0], self.cy - p[1]
        far = dx * dx + dy * dy > 1.0
        w = self.belief[which] * far
        ang = np.arctan2(dy, dx)
        c, s = float((w * np.cos(ang)).sum()), float((w * np.sin(ang)).sum())
        tot = float(w.sum()) + 1e-12
        return math.degrees(math.atan2(s, c)), math.hypot(c, s) / tot
