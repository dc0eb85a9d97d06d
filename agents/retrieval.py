"""Agents for voice-driven retrieval (sonicverse_core/tasks/retrieval.py).

* ``oracle`` (privileged: ``world``, ``person``, ``targets``): drives the geodesic shortest path to the nearest object
  of the asked category, picks it up, drives to the person, turns to face them and puts it down; proves the metrics
  (SR and SPL near 1).
* ``scripted`` (:class:`ScriptedRetriever`; the robot's own sensors and what it knows of its home: the task's
  semantic map, i.e. the floor plan, every object's category and place and its own start pose, then odometry):
  listens for the command (turning on the spot, which shows the camera the room and gives the head-turn cue),
  recognises it with :class:`agents.voice.CommandRecogniser` restricted to the categories its map holds, reports
  where it believes the speaker stands (``env.report(speaker=...)``, from the audio alone, after two voice onsets), fetches the nearest
  object of that category along the map and takes it to where the voice and the camera place the person.
* ``random``: the navigation tasks' random agent (uniform wheel velocities; it never interacts).
"""
from __future__ import annotations

import math

import numpy as np

from agents.scripted import MapDriver, _wheels

REACH = 0.45  # m: a little inside the world's 0.5 m reach
HAND_OVER = 0.85  # m from the person: the object goes down about 0.4 m in front of the robot


class OracleRetriever(MapDriver):
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
        self.tries = 0  # put-downs tried at the person (no room in front: turn a little and try again)
        self.hand_spot, self.tried = None, []

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
            self.tries, self.hand_spot = 0, another_spot(w, person, self.tried)
        goal = person if self.hand_spot is None else self.hand_spot
        close = np.hypot(*(person - w.pose[:2])) <= HAND_OVER if self.hand_spot is None else \
            np.hypot(*(self.hand_spot - w.pose[:2])) <= 0.15
        if close:
            offset = (0.0, 35.0, -35.0, 60.0, -60.0)[(self.tries // 3) % 5]
            wheels, facing = self._face(w, person, offset)
            self.tries += facing
            return self._out(wheels, stop=facing)
        return self._out(self._follow(w, goal, slow=0.3))



def another_spot(w, person, tried: list) -> np.ndarray | None:
    """A navigable place of ``w.grid`` 0.6-0.9 m from the person, 0.4 m from every place in ``tried`` (appended to), the
    nearest (geodesic) from ``w.pose`` first: where to hand an object over when there is no room in front."""
    g = w.grid
    rc = g.cell_of(person)[0]
    k = int(np.ceil(0.9 / g.config.cell)) + 1
    rr, cc = np.mgrid[rc[0] - k:rc[0] + k + 1, rc[1] - k:rc[1] + k + 1]
    xy = g.center_of(np.c_[rr.ravel(), cc.ravel()])
    d = np.hypot(*(xy - person).T)
    xy = xy[(d >= 0.6) & (d <= 0.9)]
    xy = xy[g.is_navigable(xy)]
    for t in tried:
        xy = xy[np.hypot(*(xy - t).T) > 0.4]
    if not len(xy):
        return None
    geo = g.geodesic_from_field(g.distance_field(w.pose[:2]), xy)
    spot = xy[int(np.argmin(geo))]
    tried.append(spot)
    return spot


_RECOGNISER = None


def recogniser():
    """The shipped command recogniser, loaded once per process."""
    global _RECOGNISER
    if _RECOGNISER is None:
        from agents.voice import CommandRecogniser

        _RECOGNISER = CommandRecogniser()
    return _RECOGNISER


class SpeakerBelief:
    """Where a talker stands, on a map's navigable floor (cells of ``cell`` m), from a robot's two microphones and
    optionally its depth camera; two beliefs: [0] from audio and vision (what an agent acts on), [1] from audio
    alone (what it reports as the voice's place).

    Hearing (:meth:`hear`, one block of binaural audio at the robot's map pose): each block with a voice onset
    multiplies the beliefs by the likelihood of every place given the onset-weighted interaural cross-correlation
    (the precedence effect; :func:`agents.scripted.onset_gcc_phat`), i.e. the delay the voice's direction of
    arrival would cause (its lateral angle, shrunk by the mouth's elevation above the microphones). A place in line
    of sight on the map is heard from its own direction; a place out of sight (another room, round a corner) is
    heard from the last place on its shortest way to the robot that the robot sees (a doorway, a corner), as sound
    reaches a listener in these homes. One bearing is ambiguous (front or back, and any distance along it); turning
    and moving intersect bearings. Every update is tempered (a power of 0.97 of the belief): single blocks mislead in
    reverberant rooms and no place is ruled out by hearing alone.

    Seeing (:meth:`see`): at chest and head height (1.0-1.65 m) the nearest thing in each image column is either on
    the map (a wall, a cupboard) or not: a run of columns, 0.15-0.8 m wide, whose nearest thing stands on open
    floor of the map is a person; places in view with nothing in front of them are empty; nobody stands where the
    robot is."""

    ITD_MAX = 0.00066  # s: the KEMAR head's largest interaural delay
    SHARPNESS = 1.5
    FORGET = 0.97
    FRAME = 128  # samples (8 ms at 16 kHz): onset frames short enough to end before the first reflections
    ONSET = 1.0  # onset weights (log10 energy rise - 0.3) below this carry reflections, not the direction
    # the floor seen empty is cleared only this far (m) in front of what the camera sees: a person's centre lies
    # ~0.12 m behind the front of its torso (0.2 m behind the old cylinder body), never in the cleared floor
    BODY_DEPTH = 0.15

    def __init__(self, grid, sample_rate: int, cell: float = 0.2, mouth_above_ears: float = 1.03):
        from scipy.sparse import coo_matrix

        self.grid, self.sr, self.mouth_above = grid, int(sample_rate), float(mouth_above_ears)
        g = grid
        k = max(1, int(round(cell / g.config.cell)))
        rows, cols = np.meshgrid(np.arange(k // 2, g.shape[0], k), np.arange(k // 2, g.shape[1], k), indexing="ij")
        ok = g.labels[rows, cols] == g.main_label
        self.cells = np.stack([rows[ok], cols[ok]], 1)
        self.xy = g.center_of(self.cells)
        n = len(self.xy)
        # the cells' 8-neighbour graph (the ways sound takes round corners and through doors)
        index = -np.ones(rows.shape, np.int64)
        index[ok] = np.arange(n)
        step = k * g.config.cell
        src, dst, wt = [], [], []
        for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
            r0, r1 = 0, index.shape[0] - dr
            c0, c1 = max(0, -dc), index.shape[1] - max(0, dc)
            a = index[r0:r1, c0:c1]
            b = index[r0 + dr:r1 + dr, c0 + dc:c1 + dc]
            both = (a >= 0) & (b >= 0)
            src.append(a[both])
            dst.append(b[both])
            wt.append(np.full(int(both.sum()), step * math.hypot(dr, dc)))
        src, dst, wt = np.concatenate(src), np.concatenate(dst), np.concatenate(wt)
        self.graph = coo_matrix((np.r_[wt, wt], (np.r_[src, dst], np.r_[dst, src])), shape=(n, n)).tocsr()
        self.open = g.clearance > 0.06  # what sound and sight pass (walls and furniture dilated a little)
        self._arr_key = None
        self.reset()

    def reset(self) -> None:
        """Forget everything heard and seen (the map stays)."""
        n = len(self.xy)
        self.belief = np.full((2, n), 1.0 / max(n, 1))
        self.tail = np.zeros((2, 480))
        self.noise = None
        self.t = 0.0  # s heard
        self.onsets: list[float] = []  # when voice onsets that carried a direction were heard, 1 s apart at least

    # --- hearing -------------------------------------------------------------------------------------------------
    def visible(self, p) -> np.ndarray:
        """Which cells are in line of sight of ``p`` on the map (samples every 5 cm)."""
        g = self.grid
        d = self.xy - p
        dist = np.hypot(d[:, 0], d[:, 1])
        n = int(np.ceil(dist.max() / 0.05)) + 1 if len(dist) else 1
        t = np.linspace(0.0, 1.0, n)
        vis = np.ones(len(d), bool)
        for i in range(0, n, 64):  # in slices of the samples, to bound memory
            ts = t[i:i + 64]
            pts = p + ts[:, None, None] * d[None]
            rc = g.cell_of(pts.reshape(-1, 2)).reshape(len(ts), len(d), 2)
            inside = (rc[..., 0] >= 0) & (rc[..., 0] < g.shape[0]) & (rc[..., 1] >= 0) & (rc[..., 1] < g.shape[1])
            rr, cc = np.clip(rc[..., 0], 0, g.shape[0] - 1), np.clip(rc[..., 1], 0, g.shape[1] - 1)
            # samples within 0.25 m of either end do not block (the robot's and the talker's own cells)
            near = (ts[:, None] * dist[None] < 0.25) | ((1 - ts[:, None]) * dist[None] < 0.25)
            vis &= np.all(near | (inside & self.open[rr, cc]), axis=0)
        return vis

    def arrivals(self, p) -> tuple[np.ndarray, np.ndarray]:
        """For every cell: where its voice reaches ``p`` from (x, y: the cell itself in line of sight, else the last
        place on its shortest way to ``p`` that ``p`` sees) and how far the sound travels (m). Cached per 10 cm."""
        key = tuple(np.round(np.asarray(p) / 0.1).astype(int))
        if self._arr_key == key:
            return self._arr
        from scipy.sparse.csgraph import dijkstra

        vis = self.visible(p)
        i0 = int(np.argmin(np.sum((self.xy - p) ** 2, axis=1)))
        dist, pred = dijkstra(self.graph, indices=i0, return_predecessors=True)
        idx = np.arange(len(self.xy))
        a = np.where(vis | (pred < 0), idx, pred)
        for _ in range(int(np.ceil(np.log2(max(len(idx), 2)))) + 1):  # pointer doubling: first visible ancestor
            a = np.where(vis[a], a, a[a])
        straight = np.hypot(*(self.xy - p).T)
        far = np.where(np.isfinite(dist), dist + np.hypot(*(self.xy[i0] - p)), straight)
        self._arr_key, self._arr = key, (self.xy[a], np.where(vis, straight, far))
        return self._arr

    def hear(self, audio: np.ndarray, p, yaw: float) -> bool:
        """Fold one block of binaural audio (2, n) heard at map pose ``p``, ``yaw`` degrees into both beliefs;
        whether a voice was audible in it."""
        from agents.scripted import onset_gcc_phat

        cc, weight = onset_gcc_phat(audio, self.tail, self.sr, self.ITD_MAX, frame=self.FRAME, hop=self.FRAME // 2)
        self.tail = audio[:, -self.tail.shape[1]:].astype(np.float64)
        weight = min(max(weight - self.ONSET, 0.0), 1.0)
        self.t += audio.shape[1] / self.sr
        energy = float(np.mean(audio.astype(np.float64) ** 2))
        self.noise = energy if self.noise is None else min(self.noise * 1.02 + 1e-12, max(energy, 1e-12))
        audible = energy > max(1e-9, 30.0 * self.noise)
        if not (audible and weight > 0):
            return audible
        if not self.onsets or self.t - self.onsets[-1] >= 1.0:
            self.onsets.append(self.t)
        lag = (len(cc) - 1) // 2
        ccn = (cc - cc.min()) / max(float(np.ptp(cc)), 1e-12)
        via, length = self.arrivals(p)
        d = via - p
        az = np.arctan2(d[:, 1], d[:, 0]) - math.radians(yaw)
        cos_el = length / np.hypot(length, self.mouth_above)
        expected = self.ITD_MAX * np.sin(az) * cos_el * self.sr + lag
        lik = np.interp(expected, np.arange(len(cc)), ccn)
        self.belief *= np.exp(self.SHARPNESS * weight * (lik - 1.0))[None]
        self._normalise()
        self.belief **= self.FORGET
        self._normalise()
        return audible

    def _normalise(self) -> None:
        self.belief += 1e-12
        self.belief /= self.belief.sum(axis=1, keepdims=True)

    # --- seeing --------------------------------------------------------------------------------------------------
    def see(self, depth: np.ndarray, p, yaw: float, fx: float, camera_height: float) -> np.ndarray | None:
        """Fold a depth image (H, W) seen from map pose ``p``, ``yaw`` into the acting belief; the person seen (x, y)
        or None."""
        H, W = depth.shape
        v = (np.arange(H)[:, None] - H / 2 + 0.5) / fx
        h = camera_height - v * depth
        col = np.where((depth > 0.1) & (h >= 1.0) & (h <= 1.65), depth, np.inf).min(axis=0)
        d = self.xy - p
        dist = np.hypot(d[:, 0], d[:, 1])
        ang = (np.degrees(np.arctan2(d[:, 1], d[:, 0])) - yaw + 180.0) % 360.0 - 180.0
        half = math.degrees(math.atan((W / 2) / fx)) - 3.0
        inview = (np.abs(ang) < half) & (dist > 0.6) & (dist < 6.0)
        u = np.clip(np.round(W / 2 - fx * np.tan(np.radians(np.where(inview, ang, 0.0)))).astype(int), 0, W - 1)
        empty = inview & (dist * np.cos(np.radians(ang)) + self.BODY_DEPTH < col[u])  # clearly in front
        self.belief[0, empty] *= 0.2
        self.belief[:, dist < 0.4] *= 0.1  # nobody stands where the robot is
        a = np.arctan(-(np.arange(W) - W / 2 + 0.5) / fx)
        r = col / np.cos(a)
        ok = np.isfinite(r) & (r < 6.0)
        pts = p + np.where(ok, r, 0.0)[:, None] * np.stack([np.cos(np.radians(yaw) + a), np.sin(np.radians(yaw) + a)], 1)
        g = self.grid
        rc = g.cell_of(pts)
        inside = (rc[:, 0] >= 0) & (rc[:, 0] < g.shape[0]) & (rc[:, 1] >= 0) & (rc[:, 1] < g.shape[1])
        rr, cc = np.clip(rc[:, 0], 0, g.shape[0] - 1), np.clip(rc[:, 1], 0, g.shape[1] - 1)
        odd = ok & inside & (g.clearance[rr, cc] >= 0.12)  # stands on open floor of the map
        seen = None
        i = 0
        while i < W:
            if not odd[i]:
                i += 1
                continue
            j = i
            while j + 1 < W and odd[j + 1] and abs(r[j + 1] - r[j]) < 0.15:
                j += 1
            z = float(np.median(r[i:j + 1]))
            if 0.15 <= (j - i + 1) * z / fx <= 0.8:
                b = math.radians(yaw) + float(np.mean(a[i:j + 1]))
                q = p + (z + 0.15) * np.array([math.cos(b), math.sin(b)])  # the body's centre
                self.belief[0] *= 0.5 + np.exp(-np.sum((self.xy - q) ** 2, axis=1) / (2 * 0.3 ** 2))
                seen = q
            i = j + 1
        self._normalise()
        return seen

    # --- reading ----------------------------------------------------------------------------------------------------
    def mass(self, which: int, q, r: float = 0.5) -> float:
        """The belief's mass within ``r`` m of ``q``."""
        return float(self.belief[which][np.sum((self.xy - q) ** 2, axis=1) < r * r].sum())

    def _centre(self, which: int, j: int) -> np.ndarray:
        b = self.belief[which]
        near = np.sum((self.xy - self.xy[j]) ** 2, axis=1) < 0.25
        return (b[near, None] * self.xy[near]).sum(0) / b[near].sum()

    def snap(self, q) -> np.ndarray:
        """``q`` if the robot can stand there, else the nearest cell (a person may stand where a robot cannot)."""
        q = np.asarray(q, float)
        if self.grid.is_navigable(q[None])[0]:
            return q
        return self.xy[int(np.argmin(np.sum((self.xy - q) ** 2, axis=1)))]

    def best(self, which: int = 0) -> tuple[np.ndarray, float]:
        """The densest place (the weighted centre of the most mass within 0.5 m, among the 64 likeliest cells) and
        that mass."""
        b = self.belief[which]
        top = np.argsort(b)[-64:]
        m, j = max((self.mass(which, self.xy[j]), j) for j in top)
        return self._centre(which, j), m

    def nearest_likely(self, which: int, p, share: float = 1 / 3) -> np.ndarray:
        """Of the places holding at least ``share`` of the densest place's mass, the nearest to ``p`` along the
        floor."""
        b = self.belief[which]
        top = np.argsort(b)[-96:]
        mass = np.array([self.mass(which, self.xy[j]) for j in top])
        good = top[mass >= mass.max() * share]
        _, length = self.arrivals(p)
        return self._centre(which, int(good[int(np.argmin(length[good]))]))


class _Me:
    """The robot as the oracle's helpers see a world: its pose (odometry on the map), the map's grid, a bump."""

    def __init__(self, grid):
        self.grid, self.pose, self.bumped = grid, np.zeros(3), False


class ScriptedRetriever(MapDriver):
    """Voice retrieval from the robot's sensors and its semantic map. It listens for the command while turning on
    the spot and recognises it (restricted to the categories on its map); fetches the nearest object of that
    category along the map; delivers it to the nearest likely place of the person (:class:`SpeakerBelief`, audio
    and vision), putting it down once it sees a person there within 0.85 m (without a camera: at the voice's
    likeliest place); a likely place it looks at for a second and finds empty is dropped. It reports where the voice
    alone places the speaker once it has understood the command and heard two voice onsets that carried a direction
    at least a second apart (an utterance's first onset carries its direction in these reverberant rooms and little
    else does; one direction leaves front and back open, a second heard after the robot turned or moved settles
    it), or else when it puts the object down."""

    name = "scripted"
    CELL = 0.2  # m: the belief's cells
    LISTEN_TURN = 90.0  # deg/s while listening for the command

    def reset(self, env, obs, info):
        super().reset(env, obs, info)
        from sonicverse_core.tasks.retrieval import SPOKEN

        self.sr = env.cfg.sample_rate
        self.map = m = env.semantic_map()
        self.grid = m.grid
        self.me = _Me(m.grid)
        self.me.pose[:] = (*m.start[:2], m.start[2])
        self.ears = SpeakerBelief(m.grid, self.sr, self.CELL)
        self._fx = (env.cfg.width / 2) / math.tan(math.radians(env.cfg.hfov) / 2)
        self.speech: list[np.ndarray] = []
        self.quiet = 0
        self.phase = "listen"
        self.category = None
        self.target = self.spot = None
        self.tries, self.hand_spot, self.tried = 0, None, []
        self.seen_at: tuple | None = None  # (xy, step) of the last person seen
        self.goal_xy = None
        self.stare = 0
        self.reported = False
        self.steps = 0
        self.allowed = sorted({o.category for o in m.objects if o.movable} & set(SPOKEN))

    def act(self, obs, info):
        self.steps += 1
        self.blind = "depth" not in obs
        p, yaw = self.map.to_map(obs["pose"])
        self.me.pose[:] = (p[0], p[1], yaw)
        self.me.bumped = obs.get("bump") is not None and obs["bump"][0] > 0
        audible = self.ears.hear(obs["audio"], p, yaw)
        if not self.reported and len(self.ears.onsets) >= 2 and self.category is not None:
            self._report()
        if "depth" in obs:
            seen = self.ears.see(obs["depth"][..., 0], p, yaw, self._fx, self.robot.camera_height)
            if seen is not None:
                self.seen_at = (seen, self.steps)
        if self.phase == "listen":
            return self._listen(obs["audio"], audible)
        if info.get("carrying") is None:
            return self._fetch(p)
        return self._deliver(p)

    def _listen(self, audio, audible):
        if audible or self.speech:
            self.speech.append(audio.mean(axis=0))
            self.quiet = 0 if audible else self.quiet + 1
            if self.quiet * self.dt >= 0.4:  # the utterance is over
                x = np.concatenate(self.speech)
                self.speech, self.quiet = [], 0
                if len(x) >= 0.4 * self.sr:
                    r = recogniser().recognise(x, self.sr, allowed=self.allowed or None)
                    if r.category != "other":
                        self.category = r.category
                        self._start_fetch()
        return self._out(_wheels(0.0, math.radians(self.LISTEN_TURN), self.robot))

    def _report(self) -> None:
        est, _ = self.ears.best(1)
        self.env.report(speaker=(float(est[0]), float(est[1])))
        self.reported = True

    def _start_fetch(self) -> None:
        from sonicverse_core.tasks.retrieval import approach_cells

        g, p = self.grid, self.me.pose[:2]
        f = g.distance_field(p)
        best = (np.inf, None, None)
        for o in self.map.objects:
            if o.movable and o.category == self.category:
                q = approach_cells(g, o.lo, o.hi, self.robot.radius + REACH)
                if len(q):
                    d = g.geodesic_from_field(f, q)
                    i = int(np.argmin(d))
                    if d[i] < best[0]:
                        best = (float(d[i]), o, q[i])
        _, self.target, self.spot = best
        self.phase = "fetch"

    def _reach(self, o) -> float:
        p = self.me.pose[:2]
        gap = np.maximum(np.maximum(np.array(o.lo[:2]) - p, p - np.array(o.hi[:2])), 0.0)
        return float(np.hypot(*gap)) - self.robot.radius

    def _fetch(self, p):
        if self.target is None:
            return self._out([0.0, 0.0])
        if self._reach(self.target) <= REACH:
            wheels, facing = self._face(self.me, self.target.position[:2])
            return self._out(wheels, stop=facing)
        return self._out(self._follow(self.me, self.spot, slow=0.3))

    def _goal(self, p) -> np.ndarray:
        """Where to look for the person: the nearest likely place, kept while it stays likely (a quarter of the
        densest place's mass; no dithering between equals)."""
        _, top = self.ears.best(0)
        if self.goal_xy is None or self.ears.mass(0, self.goal_xy) < top / 4.0:
            self.goal_xy = self.ears.nearest_likely(0, p)
        return self.goal_xy

    def _deliver(self, p):
        goal = self._goal(p)
        seen = self.seen_at is not None and self.steps - self.seen_at[1] <= 20 and \
            np.hypot(*(self.seen_at[0] - goal)) < 0.6
        if self.blind:  # no camera: trust the voice's likeliest place
            goal, _ = self.ears.best(0)
            seen = True
        if self.tries >= 15:
            self.tries, self.hand_spot = 0, another_spot(self.me, goal, self.tried)
        if self.hand_spot is not None and np.hypot(*(self.hand_spot - goal)) > 1.2:
            self.hand_spot = None  # the belief moved on
        d = float(np.hypot(*(goal - p)))
        close = d <= HAND_OVER if self.hand_spot is None else np.hypot(*(self.hand_spot - p)) <= 0.15
        if close and seen:
            offset = (0.0, 35.0, -35.0, 60.0, -60.0)[(self.tries // 3) % 5]
            wheels, facing = self._face(self.me, goal, offset)
            self.tries += facing
            if facing and not self.reported:  # putting it down ends the episode: say where the voice was now
                self._report()
            return self._out(wheels, stop=facing)
        if close:  # nobody seen there yet: look at it (the camera then clears it or finds them)
            wheels, facing = self._face(self.me, goal)
            self.stare = self.stare + 1 if facing else 0
            if self.stare > 10:  # looked for a second and nobody: not there
                e = self.ears
                e.belief[0, np.sum((e.xy - goal) ** 2, axis=1) < 0.36] *= 0.05
                e._normalise()
                self.goal_xy, self.stare = None, 0
            return self._out(wheels)
        to = self.ears.snap(goal) if self.hand_spot is None else self.hand_spot
        return self._out(self._follow(self.me, to, slow=0.3))
