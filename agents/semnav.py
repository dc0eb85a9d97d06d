"""``sem-nav``: a scripted semantic audio-visual navigator for SemanticAudioNav (and AudioGoal).

It names the sounding object's category by ear, explores until its semantic camera sees an object of that category,
drives beside the nearest one and stops there. It reads observations only: the spectrogram (named by the shipped
SAVi's goal predictor, :func:`agents.navmap.sound_classifier`), depth (an occupancy and floor map, as the ``gan``
baseline's), the semantic camera and odometry.

The semantic camera's category ids are ground truth (the scene's labels, as Habitat's semantic sensor): a stand-in
for an object detector on RGB. So this agent knows *what* it sees for free, and the ears only have to say which
category to look for; it does not know which of the category's objects sounded (it takes the nearest it has seen).

Per step:

* it maps depth (obstacles 0.08-0.6 m above the floor; the floor it sees) and the semantic image (a bit per
  category per 0.1 m cell, any height);
* while the goal sounds (the spectrogram's mean above ``agents.savi.AUDIBLE``) it adds the goal predictor's
  log-probabilities; the category is their argmax (after ``MIN_HEARD`` audible steps);
* it first turns once on the spot, seeing and hearing all round. From the turn it takes the sound's bearing (the
  level difference between the ears against the heading, :meth:`SemNavAgent._fit_bearing`; it points along the
  first stretch of the path, through the doorway the sound comes by) and how far the sound is (the turn's level
  and the named category, :data:`LEVEL_FIT`);
* with a category and a sighting of it: it plans (Dijkstra on the map, obstacles dilated by the robot's radius) to
  a reachable free cell beside the sighted cluster, drives there, turns to face it and stops (a stop action; on
  AudioGoal the task ends on arrival, and where it does not, the next sighting). Among several clusters it takes
  the one cheapest to reach, off the bearing least and nearest the distance the level said; one much nearer or
  farther than that (``LEVEL_REJECT``) is passed over until ``LATE`` of the episode has gone;
* otherwise it explores: the frontier (seen floor beside unmapped space) cheapest by path length plus its
  angle off the bearing, re-chosen every ``REPLAN`` steps;
* a path that the dilated map sends the long way round (a doorway shut by a door leaf's dilation, unmapped space
  still open round it) is taken on the map dilated less where that is ``SQUEEZE_M`` shorter
  (:meth:`SemNavAgent._squeeze`);
* where the sound never stops (AudioGoal: no stop action), it also keeps hearing: the turn's bearing and level and a
  level every ``WINDOW`` audible steps while driving go into the ``gan`` baseline's probability grid of where the
  goal is (:class:`agents.gan.GanAgent`, ``self.post``: the levels' shared-error Gaussian on the path distance, the
  bearing's von Mises term), and that grid, not the first turn's bearing and level, weighs frontiers and sightings
  (``POST_M`` m of path per nat below its best, :meth:`SemNavAgent._post_cost`); a sighting it stood beside without
  the episode ending is ruled out of the grid (session 53: 87 -> 99 arrivals in 160 validation episodes; README);
* a bump maps an obstacle where the robot touched (a door leaf seen edge-on escapes the camera) and backs off;
* at its last step it stops wherever it is (a stop that fails costs nothing more than none).
"""
from __future__ import annotations

import math

import numpy as np

from agents.scripted import MapAgent, _pursue, _wheels, grid_field, grid_trace, map_depth, turn_steps, turn_toward


def ild(audio: np.ndarray, sr: int) -> float:
    """The level difference left - right (dB) of a binaural block in 0.7-4 kHz."""
    from scipy.signal import butter, sosfilt

    key = sr
    if key not in _BAND:
        _BAND[key] = butter(4, [700, 4000], "band", fs=sr, output="sos")
    e = (sosfilt(_BAND[key], np.asarray(audio, float), axis=1) ** 2).sum(1) + 1e-12
    return float(10 * math.log10(e[0] / e[1]))


_BAND: dict = {}

# ln(path distance from the start to the goal, m) = slope x (the spin's level, dB) + the category's offset: least
# squares over 500 training episodes, `fit_level(500, seed=1)` (residual 0.387 in ln units, a factor of 1.47, where
# the distances alone spread 0.56). Made on session 41's sound; re-fit when the sound changes. It assumes the tasks'
# default source gain (TaskConfig.source_gain (1, 1)): with the sim-to-real range, the distance is off by the gain
LEVEL_FIT = {"slope": -0.067, "offset": {
    "straight_chair": -0.37, "breakfast_table": -1.27, "picture": -0.57, "bottom_cabinet": -1.63, "cushion": -1.0,
    "sofa": -0.22, "bed": -0.42, "shelf": -0.69, "sink": -1.07, "toilet": -0.26,
    "stool": -0.73, "standing_tv": -0.84, "shower": -0.42, "bathtub": -0.66, "countertop": -1.17}}


def fit_bearing(turn) -> float | None:
    """The bearing (world yaw, radians) a sound comes from, fitted to a turn on the spot's (yaw radians, ILD dB)
    pairs (:func:`ild`) as ILD = c + A sin(b - yaw) (the left ear louder when the sound is on the left); None from
    fewer than 8 pairs."""
    if len(turn) < 8:
        return None
    th, d = np.array(turn, float).T
    coef = np.linalg.lstsq(np.c_[np.ones(len(th)), np.cos(th), -np.sin(th)], d, rcond=None)[0]
    return math.atan2(coef[1], coef[2]) if math.hypot(coef[1], coef[2]) > 0.0 else None


def spin_level(env) -> float:
    """Turn once on the spot in ``env`` (just reset; the task's stop action held off) as :class:`SemNavAgent`
    does, and return the level (dB) it hears after the turn's steps 3 to 20 (the agent acts on step 21's
    observation): what :data:`LEVEL_FIT` reads."""
    robot, dt = env.unwrapped.robot, env.unwrapped.cfg.step_seconds
    turn = _wheels(0.0, math.radians(robot.max_turn_deg), robot)
    act = np.r_[turn, -1.0][:env.action_space.shape[0]].astype(np.float32)
    e = []
    for t in range(turn_steps(robot, dt) - 1):
        obs, *_ = env.step(act)
        if t >= 2:
            e.append(float(np.mean(np.square(np.asarray(obs["audio"], float)))))
    return 10 * math.log10(np.mean(e) + 1e-20)


def level_rows(episodes: int, seed: int, split: str = "train") -> list[tuple[str, float, float]]:
    """Per SemanticAudioNav episode of ``split`` (heard sounds; episode i seeded as `sonicverse eval --seed` seeds
    it): its category, the first spin's level (:func:`spin_level`) and the path distance from the start to the
    nearest terminal position."""
    from sonicverse_core.tasks import make_env

    env = make_env("SemanticAudioNav", split=split, sounds="heard", sensors=("audio", "pose"))
    rows = []
    try:
        for i in range(episodes):
            env.reset(seed=int(np.random.SeedSequence([seed, i]).generate_state(1)[0]))
            ep = env.unwrapped.episode
            rows.append((ep.category, spin_level(env), float(ep.geodesic)))
    finally:
        env.close()
    return rows


def fit_level(episodes: int = 500, seed: int = 1, split: str = "train") -> dict:
    """:data:`LEVEL_FIT` from ``episodes`` episodes of ``split`` (:func:`level_rows`; training homes only): least
    squares of the distance's logarithm on the level plus one offset per category. Returns the fit and its
    residual standard deviation (``resid``, in ln units)."""
    from assets_manifest.soundbank import CATEGORIES

    rows = level_rows(episodes, seed, split)
    k = np.array([CATEGORIES.index(c) for c, _, _ in rows])
    lv, geo = np.array([r[1] for r in rows]), np.array([r[2] for r in rows])
    X = np.zeros((len(rows), 1 + len(CATEGORIES)))
    X[:, 0], X[np.arange(len(rows)), 1 + k] = lv, 1.0
    coef = np.linalg.lstsq(X, np.log(geo), rcond=None)[0]
    resid = float(np.std(np.log(geo) - X @ coef))
    return {"slope": round(float(coef[0]), 4), "offset": {c: round(float(v), 2) for c, v in zip(CATEGORIES, coef[1:])},
            "resid": round(resid, 3), "episodes": episodes}


class SemNavAgent(MapAgent):
    """See the module's docstring."""

    name = "sem-nav"
    MIN_HEARD = 3  # audible steps before the category is trusted
    REPLAN = 10  # steps between re-planning
    FRONTIER_MIN = 1.0  # m: frontiers nearer than this are not worth a drive
    ARRIVE = 0.15  # m from the approach cell: arrived
    APPROACH = 1.0  # m: the approach cell lies within this of the target's sighted cells
    INFLATE = 2  # cells of obstacle dilation (0.2 m, about the robot's radius)
    BACKOFF = 3  # steps reversing after a bump
    GAP_W = 4.0  # m of driving worth 1 m nearer the object at the stop
    SWITCH_M = 2.0  # m better another sighting must score to be taken instead of the one it drives to
    DILATE_LESS = True  # no frontier on the dilated map: look again on maps dilated less before wandering
    SQUEEZE_M = 1.5  # m: take the path on a map dilated less when it is this much shorter (None: never; session 64)
    LEVEL_REJECT = 1.0  # |ln(distance / the level's)| beyond which a sighting is passed over (2.5 sigma of the fit)
    LATE = 0.7  # after this share of the steps, every sighting counts
    LEVEL_M = 3.0  # m of path a sighting costs per unit of |ln(its distance from the start / the level's)|
    BEARING_M = 3.0  # m of path a goal 180 degrees off the heard bearing costs more than one on it (half at 90)
    POSTERIOR = True  # where the sound never stops (AudioGoal): weigh places by the gan's grid (see _post_cost)
    POST_M = 2.5  # m of path per nat of log-posterior below the grid's best
    POST_REACH = 1.0  # m: a place is worth the best cell of the grid within this of it
    POST_REJECT = 6.0  # nats below the best: a sighting passed over until LATE
    # m: where someone else drives (a route map's policy, which seldom ends on the approach cell), it also counts itself
    # arrived once the robot is this close to its target's sighted cells, or no farther from them than the approach
    # cell is plus BESIDE_TOL (:meth:`_beside`); None: only at the approach cell (sem-nav driving itself)
    BESIDE_M: float | None = None
    BESIDE_TOL = 0.1

    def env_kwargs(self) -> dict:
        return {"sensors": ("depth", "semantic", "spectrogram", "audio", "pose", "bump")}

    def reset(self, env, obs, info):
        super().reset(env, obs, info)
        from agents.navmap import SoundNamer, category_bits

        self.bit, self.lut = category_bits()
        self.seen = np.zeros((self.SIZE, self.SIZE), np.int64)
        self.floor = np.zeros((self.SIZE, self.SIZE), bool)
        self.ears = SoundNamer()
        self.max_steps = int(env.cfg.max_steps)
        self.steps = 0
        self.full_turn = turn_steps(self.robot, self.dt)
        self.spin_left = self.full_turn
        self.path, self.k, self.since_plan = None, 0, self.REPLAN
        self.target = None  # (approach xy, the cluster's cells' xy) once the category is seen
        self.mode = "spin"
        self.facing = 0
        self.visited: list[np.ndarray] = []  # approach cells already stopped at (AudioGoal goes on after a stop)
        self.backoff = 0
        self.sr = env.cfg.sample_rate
        self.turn = []  # (yaw, ILD dB) of the audible steps of the first spin
        self.bearing, self.spun_at = None, None  # the sound's direction from the spin (world yaw, radians)
        self.spin_e, self.level_db = [], None  # the level heard over the spin
        self.post, self.window = None, []  # AudioGoal: the gan's grid, fed the spin and levels heard while driving
        self._post_key, self._post_near = None, None  # _post_cost: what its filtered grid came from, the grid
        if self.POSTERIOR and not self.stop_dim and "audio" in obs:
            from agents.gan import GanAgent

            self.post = GanAgent(self.rng)
            self.post.reset(env, obs, info)
            self.post.occ, self.post.ears = self.occ, self.ears  # one depth map, one pair of ears

    # --- what it knows ----------------------------------------------------------------------------------------
    def category(self) -> int:
        """The index (into CATEGORIES) the ears name so far; -1 before ``MIN_HEARD`` audible steps."""
        return self.ears.category(self.MIN_HEARD)

    def _observe(self, obs, p, yaw) -> None:
        from agents.navmap import map_semantic

        if "semantic" not in obs or "depth" not in obs:
            from sonicverse_core.errors import ConfigError

            raise ConfigError("sem-nav needs the env's 'depth' and 'semantic' sensors")
        depth = np.asarray(obs["depth"])[..., 0]
        map_depth(self.occ, depth, p, yaw, self._fx, self.robot.camera_height, self.CELL, floor=self.floor)
        map_semantic(self.seen, depth, np.asarray(obs["semantic"])[..., 0], self.lut, p, yaw, self._fx, self.CELL)
        if 0 < self.spin_left <= self.full_turn - 3 and "audio" in obs:  # the spin's level (:func:`spin_level`)
            self.spin_e.append(float(np.mean(np.square(np.asarray(obs["audio"], float)))))
        heard = self.ears.hear(obs["spectrogram"])
        if heard and self.spin_left > 0 and "audio" in obs:
            self.turn.append((math.radians(yaw), ild(np.asarray(obs["audio"]), self.sr)))
        if self.post is not None and self.spin_left == 0:  # a level per WINDOW audible steps while driving
            if not heard:
                self.window = []
                return
            self.window.append((np.array(p, float), float(np.mean(np.square(np.asarray(obs["audio"], float))))))
            if len(self.window) >= self.post.WINDOW:
                pos = np.mean([w[0] for w in self.window], axis=0)
                self.post.add_level(pos, 10 * math.log10(np.mean([w[1] for w in self.window]) + 1e-20), False)
                self.window = []

    def expected_distance(self) -> float | None:
        """The goal's path distance from the start (m) that the level of the first spin suggests for the category
        the ears name (:data:`LEVEL_FIT`); None before both are known."""
        k = self.category()
        if self.level_db is None or k < 0:
            return None
        from assets_manifest.soundbank import CATEGORIES

        slope, offset = LEVEL_FIT["slope"], LEVEL_FIT["offset"][CATEGORIES[k]]
        return float(math.exp(slope * self.level_db + offset))

    def _fit_bearing(self, p) -> None:
        """The sound's direction from the spin: the level difference between the ears (0.7-4 kHz) against the
        heading, fitted as c + A sin(b - yaw) (the left ear louder when the sound is on the left); b is the bearing.
        Over 20 validation episodes its median error to the first 1.5 m of the shortest path was 43 degrees (chance:
        90); to the straight line to the goal, 59."""
        self.spun_at = np.array(p, float)
        b = fit_bearing(self.turn)
        if b is not None:
            self.bearing = b

    def _off_bearing(self, xy) -> np.ndarray:
        """Per point, 1 - cos of its angle off the heard bearing as seen from where the robot spun (0: none)."""
        if self.bearing is None:
            return np.zeros(len(xy))
        v = np.asarray(xy, float) - self.spun_at
        return 1.0 - np.cos(np.arctan2(v[:, 1], v[:, 0]) - self.bearing)

    def _xy(self, cells) -> np.ndarray:
        return (np.asarray(cells, float) - self.SIZE // 2 + 0.5) * self.CELL

    def _post_cost(self, cells) -> np.ndarray | None:
        """Per map cell of ``cells``, ``POST_M`` m per nat that the gan's grid's best within ``POST_REACH`` of it
        falls below the grid's best; None without a grid (or before it holds a level and a category)."""
        if self.post is None:
            return None
        lp = self.post.log_posterior()
        if lp is None or not np.isfinite(lp).any():
            return None
        key = (self.ears.category(), len(self.post.levels), len(self.post.bearings), int(self.post.ruled_out.sum()),
               int((self.occ >= 2).sum()))
        if self._post_key != key:
            from scipy.ndimage import maximum_filter

            r = int(round(self.POST_REACH / self.post.POST_CELL))
            near = maximum_filter(np.where(np.isfinite(lp), lp, -1e9), size=2 * r + 1)
            self._post_key, self._post_near = key, near.max() - near
        g = np.clip(np.asarray(cells) // self.post.f, 0, self.post.n - 1)
        return self.POST_M * self._post_near[g[:, 0], g[:, 1]]

    # --- deciding where to go ---------------------------------------------------------------------------------
    def _choose(self, p) -> None:
        """Plan: to the named category's best sighting if there is one (:meth:`_sighting`), else to the frontier
        cheapest by path plus its angle off the bearing (:meth:`_frontier`), else to a random reachable cell. When
        the map, its obstacles dilated by the robot's radius, shuts the robot in a pocket with no frontier (a gap
        between furniture narrower than the dilation, or bump marks), it looks for frontiers on the map dilated less
        (``DILATE_LESS``) before it wanders, and then wanders on the least dilated map (the one it looked on last)."""
        plans: dict = {}  # this plan's searches by dilation (the squeeze below asks for the same maps again)

        def reach(k: int):
            if k not in plans:
                plans[k] = self._reachable(p, k)
            return plans[k]

        s, blocked, dist, pred = reach(self.INFLATE)
        goal, self.mode = self._sighting(blocked, dist), "approach"
        if goal is None:
            self.target, self.mode = None, "explore"
            goal = self._frontier(blocked, dist)
            for k in range(self.INFLATE - 1, -1, -1) if self.DILATE_LESS else ():
                if goal is not None:
                    break
                s, blocked, dist, pred = reach(k)
                goal = self._frontier(blocked, dist)
        if goal is None:  # nothing left to explore on the map: wander to a random reachable cell (of the last map)
            cand = np.argwhere(np.isfinite(dist) & (dist * self.CELL >= self.FRONTIER_MIN))
            if len(cand):
                goal = cand[int(self.rng.integers(len(cand)))]
        cells = grid_trace(pred, self.SIZE, s, goal) if goal is not None else None
        if cells and self.SQUEEZE_M is not None:
            cells = self._squeeze(goal, dist, cells, reach)
        self.path = self._xy(cells) if cells else np.array([p])
        self.k = min(2, len(self.path) - 1)
        self.since_plan = 0

    def _squeeze(self, goal, dist: np.ndarray, cells: list, reach) -> list:
        """The path to ``goal`` on the map dilated less (``INFLATE - 1`` cells, then none) where it is ``SQUEEZE_M``
        shorter than ``cells`` (``dist``'s path); else ``cells``. ``reach(k)``: :meth:`_reachable` on the map dilated
        ``k`` cells from the robot's cell, each searched once a plan. An open door's leaf, seen edge-on in the doorway,
        dilated with the frame can shut the doorway on the dilated map while unmapped space still offers a way round:
        the robot turned back in the doorway of the room it was driving to and spent its last 400 steps on the way
        round (validation episode 43 of SemanticAudioNav, session 64)."""
        d0 = float(dist[goal[0], goal[1]])
        for k in range(self.INFLATE - 1, -1, -1):
            s, _, d, pred = reach(k)
            if np.isfinite(d[goal[0], goal[1]]) and (d0 - float(d[goal[0], goal[1]])) * self.CELL > self.SQUEEZE_M:
                return grid_trace(pred, self.SIZE, s, goal) or cells
        return cells

    def _frontier(self, blocked: np.ndarray, dist: np.ndarray):
        """The frontier cell (seen floor beside unmapped space) at least ``FRONTIER_MIN`` away cheapest by path
        plus its angle off the bearing (or the gan's grid where it has one, :meth:`_post_cost`); None if none."""
        from scipy.ndimage import binary_dilation

        unknown = (self.occ < 2) & ~self.floor
        front = self.floor & ~blocked & binary_dilation(unknown) & np.isfinite(dist)
        front &= dist * self.CELL >= self.FRONTIER_MIN
        if not front.any():
            return None
        cand = np.argwhere(front)
        pc = self._post_cost(cand)
        cost = dist[cand[:, 0], cand[:, 1]] * self.CELL + (
            self.BEARING_M * self._off_bearing(self._xy(cand)) if pc is None else pc)
        return cand[int(np.argmin(cost))]

    def _sighting(self, blocked: np.ndarray, dist: np.ndarray):
        """The cell to stop at beside the named category's best sighted cluster (sightings within 0.2 m), and
        ``self.target`` set to (that cell's xy, the cluster's cells' xy); None when there is none to go to. Per
        cluster: the reachable free cell (seen floor, where there is some) within ``APPROACH`` of it cheapest by
        path plus ``GAP_W`` times its gap to the cluster; the cluster's score adds its angle off the bearing and
        how far its distance from the start is from the level's (one off by more than ``LEVEL_REJECT`` is passed
        over before ``LATE``). The cluster it drives to is kept unless another scores ``SWITCH_M`` better."""
        from scipy.ndimage import binary_dilation, label

        k = self.category()
        if k < 0:
            return None
        mine = ((self.seen >> self.bit[k]) & 1).astype(bool)
        if not mine.any():
            return None
        lab, n = label(binary_dilation(mine, iterations=2))
        r = int(round(self.APPROACH / self.CELL))
        far = self.expected_distance()  # which of them: the one as far from the start as it sounded
        if far is not None:
            o = np.clip(self._cell(np.zeros(2)), 0, self.SIZE - 1)  # where it started (and turned)
            b0 = blocked.copy()
            b0[o[0], o[1]] = False
            from_start = grid_field(b0, o)[0].reshape(self.SIZE, self.SIZE)
        best, keep = None, None
        for i in range(1, n + 1):
            cells = np.argwhere((lab == i) & mine)
            xy = self._xy(cells)
            if any(np.hypot(*(xy - v).T).min() < self.APPROACH for v in self.visited):
                continue
            near = binary_dilation(mine & (lab == i), iterations=r) & np.isfinite(dist) & ~blocked
            if (near & self.floor).any():
                near &= self.floor
            if not near.any():
                continue
            cand = np.argwhere(near)
            gap = np.min(np.hypot(*(cand[:, None, :] - cells[None, :, :]).transpose(2, 0, 1)), axis=1)
            cost = (dist[cand[:, 0], cand[:, 1]] + self.GAP_W * gap) * self.CELL
            j = int(np.argmin(cost))
            pc = self._post_cost(np.vstack([cand[j][None], cells]))
            if pc is not None:  # the grid holds the bearings and every level heard
                if float(np.min(pc)) > self.POST_M * self.POST_REJECT and self.steps < self.LATE * self.max_steps:
                    continue
                score = float(cost[j]) + float(np.min(pc))
            else:
                score = float(cost[j]) + self.BEARING_M * float(np.min(self._off_bearing(xy)))
            if pc is None and far is not None and np.isfinite(from_start[cand[j, 0], cand[j, 1]]):
                off = abs(math.log(max(from_start[cand[j, 0], cand[j, 1]] * self.CELL, 0.5) / far))
                if off > self.LEVEL_REJECT and self.steps < self.LATE * self.max_steps:
                    continue  # not where it sounded: look on while there is time
                score += self.LEVEL_M * off
            if best is None or score < best[0]:
                best = (score, cand[j], xy)
            if self.target is not None and np.min(np.hypot(*(xy - self.target[1][0]).T)) < 0.3:
                keep = (score, cand[j], xy)  # the cluster it was driving to
        if keep is not None and keep[0] < best[0] + self.SWITCH_M:
            best = keep
        if best is None:
            return None
        self.target = (self._xy(best[1]), best[2])
        return best[1]

    def act(self, obs, info):
        p, yaw = self._pose(obs)
        if self.mode == "approach" and self._beside(p):
            self.mode = "face"
        self._observe(obs, p, yaw)
        self.steps += 1
        if self.stop_dim and self.steps >= self.max_steps:
            return self._out([0.0, 0.0], stop=True)
        turn = _wheels(0.0, math.radians(self.robot.max_turn_deg), self.robot)
        if self.spin_left > 0:
            self.spin_left -= 1
            if self.spin_left == 0:
                self._fit_bearing(p)
                if self.spin_e:
                    self.level_db = 10 * math.log10(np.mean(self.spin_e) + 1e-20)
                if self.post is not None:
                    if self.bearing is not None:
                        self.post.bearings.append((self.spun_at.copy(), self.bearing))
                    if len(self.spin_e) >= 5:
                        self.post.add_level(self.spun_at.copy(), self.level_db, True)
                self.since_plan = self.REPLAN
            return self._out(turn)
        bumped = obs.get("bump") is not None and obs["bump"][0] > 0
        if bumped and self.mode != "face":  # something the camera missed (a door leaf edge-on): map it, back off
            self._mark_contact(p, yaw)
            self.backoff = self.BACKOFF
        if self.backoff > 0:
            self.backoff -= 1
            if self.backoff == 0:
                self.since_plan = self.REPLAN
            return self._out(_wheels(-0.3 * self.robot.max_speed, 0.0, self.robot))
        if self.mode == "face":
            return self._face_target(p, yaw)
        self.since_plan += 1
        if self.path is None or self.since_plan >= self.REPLAN:
            self._choose(p)
        if self.mode == "approach" and np.linalg.norm(self.target[0] - p) < self.ARRIVE:
            self.mode = "face"
            return self._face_target(p, yaw)
        while self.k < len(self.path) - 1 and np.linalg.norm(self.path[self.k] - p) < 0.2:
            self.k += 1
        if len(self.path) < 2 or (self.k >= len(self.path) - 1 and np.linalg.norm(self.path[-1] - p) < 0.1):
            self.since_plan = self.REPLAN  # arrived at a frontier (or nowhere to go): choose again next step
            return self._out(turn)
        return self._out(_pursue(p, yaw, self.path[self.k], self.robot, self.dt,
                                 slow_within=0.3 if self.mode == "approach" else 0.0))

    def _beside(self, p) -> bool:
        """Whether the robot at ``p`` is beside the target it approaches, given ``BESIDE_M`` (else False): within
        ``BESIDE_M`` of the target's sighted cells, or no farther from them than the approach cell plus
        ``BESIDE_TOL``. Only where the task has a stop action: on AudioGoal a face there marks the sighting visited.
        A policy that drives up to a shower (sighted floor: the approach cell inside it) or pins itself against the
        object an arm's length from the approach cell is beside it, and the route then shows the line to face it."""
        if self.BESIDE_M is None or not self.stop_dim or self.target is None:
            return False
        cells = self.target[1]
        here = float(np.min(np.linalg.norm(cells - p, axis=1)))
        there = float(np.min(np.linalg.norm(cells - self.target[0], axis=1)))
        return here <= max(there + self.BESIDE_TOL, self.BESIDE_M)

    def _mark_contact(self, p, yaw) -> None:
        """A bump: obstacle cells where the robot's front touched (ahead and 30 degrees either side)."""
        for a in (-30.0, 0.0, 30.0):
            b = math.radians(yaw + a)
            c = self._cell(p + (self.robot.radius + 0.05) * np.array([math.cos(b), math.sin(b)]))
            if 0 <= c[0] < self.SIZE and 0 <= c[1] < self.SIZE:
                self.occ[c[0], c[1]] = max(int(self.occ[c[0], c[1]]), 2)

    def _face_target(self, p, yaw):
        """Turn to the target's nearest sighted cell, then stop (or, without a stop action, wait)."""
        cells = self.target[1]
        q = cells[int(np.argmin(np.linalg.norm(cells - p, axis=1)))]
        wheels, facing = turn_toward(p, yaw, q, self.robot, self.dt, tol=10.0)
        self.facing += 1
        if facing or self.facing > 20:
            if not self.stop_dim:  # AudioGoal: not ended here, so not this one; try the next sighting
                self.visited.append(self.target[0])
                if self.post is not None:
                    n = self.post.n
                    i, j = np.clip(np.floor(p / self.post.POST_CELL).astype(int) + n // 2, 0, n - 1)
                    self.post.ruled_out[max(0, i - 1):i + 2, max(0, j - 1):j + 2] = True
                self.mode, self.facing, self.since_plan = "explore", 0, self.REPLAN
            return self._out([0.0, 0.0], stop=True)
        return self._out(wheels)


class RouteTeacher(SemNavAgent):
    """sem-nav as the shipped route policies' README figures were measured with (``train --map route``: ``av-nav``,
    ``savi`` and ``multitask`` on SemanticAudioNav, ``av-nav`` on AudioGoal) and, but for session 53's AudioGoal
    grid, as they were trained on it: it wanders where the dilated map shuts it in (before session 55) and keeps the
    dilated map's way round a doorway it shuts (before session 64). Its drawn
    route is those policies' input, so a changed teacher would change what every shipped checkpoint sees; a
    retrain on :class:`SemNavAgent` would carry the fix to them."""

    DILATE_LESS = False
    SQUEEZE_M = None
