"""``gan``: the Gan et al. (2020) baseline: hear where the goal is, map free space from depth, plan to the estimate.

Gan et al. localise the sounding goal with a network trained on the audio and drive to the estimate with a planner on
a depth occupancy map. Ours once did that with a learned localiser (:class:`agents.scripted.GanLocalizerAgent`, still
runnable as ``--agent agents.scripted:GanLocalizerAgent``): it reached 1% on SemanticAudioNav, because a single
step's binaural spectrogram says almost nothing about where a sound plays in these reverberant homes (the localiser's
bearing is at chance: ``agents/checkpoints/sound-localizer.md``), so the robot drove to noise. Two cues do carry the
location, and this agent combines them in a probability grid over where the goal is:

* **direction**: turning once on the spot, the level difference between the ears against the heading
  (:func:`agents.semnav.fit_bearing`) gives the bearing the sound arrives from: the first stretch of the path to it
  (through the doorway it comes by);
* **distance**: how loud it is, for the category the ears name (:class:`agents.navmap.SoundNamer`), says how far
  the goal is by path (:data:`agents.semnav.LEVEL_FIT`, fitted on training homes). Heard at several places (the
  spins, and every ``WINDOW`` audible steps while driving), the levels trilaterate it. The errors of one episode's
  levels share a part (a recording louder than its category's typical one, a reverberant home) and the grid models
  that: ln distance = fit + a shared error (``SIGMA_SHARED``) + an error per place (``SIGMA_SPIN``,
  ``SIGMA_DRIVE``), so what counts most is how the level *changes* from place to place.

Per cell of a 0.2 m grid over the odometry frame, the log-posterior adds a von Mises term for each spin's bearing
(seen from where it spun) and the levels' Gaussian term on the logarithm of the path distance from each place it
listened (Dijkstra over the depth map, unmapped space free); cells the depth camera saw as obstacles are not goals.
The robot plans (Dijkstra on the map, obstacles dilated by its radius) to the most probable cell and re-plans as the
map and the grid change. Arrived there while the sound plays, it turns on the spot again (a nearer bearing and a
louder level) and stops (tasks with a stop action) once the estimate stays within ``SETTLE`` of it; after the
sound has stopped it stops on arrival. On AudioGoal (no stop action: the episode ends on arrival) the places it has
stood and not ended are no goal. It reads observations only: depth, the spectrogram, the binaural audio, odometry
and the bump sensor. The level fits assume the tasks' default source gain (``TaskConfig.source_gain`` (1, 1)): a
louder or quieter source than the fits' places the goal nearer or farther by that factor.
"""
from __future__ import annotations

import math

import numpy as np

from agents.scripted import MapAgent, _pursue, _wheels, grid_field, grid_trace, map_depth, turn_steps


# ln(path distance to the goal's nearest stop + 1 m) = slope x (a WINDOW-step window's level heard while driving, dB)
# + the category's offset in LEVEL_FIT + shift: least squares over 522 windows of 16 steps in 80 training episodes
# driven by the oracle, `fit_drive(80, seed=7)` (residual 0.37 ln units, 0.27 within an episode; windows of 8 steps:
# 0.49 and 0.37, the sound's own rise and fall not averaged out). Re-fit when the sound changes
DRIVE_FIT = {"slope": -0.0605, "shift": 0.111}


def shared_error_loglik(res, w, shared: float) -> np.ndarray:
    """The log-density, up to a constant, of residuals ``res`` (a list of equal-shaped arrays: one per measurement,
    over the cells) that are normal with covariance diag(1 / ``w``) + ``shared``^2 (all ones): each measurement's
    own error plus one error they all share. Exact, in O(measurements) per cell (Sherman-Morrison):
    -(sum w r^2 - s^2 (sum w r)^2 / (1 + s^2 sum w)) / 2."""
    sw, swr, swr2 = 0.0, 0.0, 0.0
    for r, wi in zip(res, w):
        sw, swr, swr2 = sw + wi, swr + wi * r, swr2 + wi * r * r
    c2 = shared ** 2
    return -0.5 * (swr2 - c2 * swr * swr / (1.0 + c2 * sw))


def drive_rows(episodes: int, seed: int, split: str = "train", window: int = 8) -> list[tuple[str, int, float, float]]:
    """Per ``window`` steps of the oracle driving SemanticAudioNav episodes of ``split`` (heard sounds, played all
    episode; episode i seeded as `sonicverse eval --seed` seeds it): (category, episode, the window's level in dB,
    the path distance from the window's mean position to the nearest stop)."""
    from agents.scripted import OracleAgent
    from app.tasks.evaluate import episode_seed
    from sonicverse_core.tasks import make_env

    env = make_env("SemanticAudioNav", split=split, sounds="heard", sensors=("audio", "pose"), everlasting=True)
    u, rows = env.unwrapped, []
    try:
        for i in range(episodes):
            obs, info = env.reset(seed=episode_seed(seed, i))
            w, goals = u.home.world, np.asarray(u.privileged()["goals"])
            oracle = OracleAgent(np.random.default_rng(0))
            oracle.reset(u, obs, info)
            win, done = [], False
            while not done:
                obs, _, term, trunc, info = env.step(oracle.act(obs, info))
                done = term or trunc
                win.append((w.pose[:2].copy(), float(np.mean(np.square(obs["audio"])))))
                if len(win) == window:
                    pos = np.mean([v[0] for v in win], axis=0)
                    path = float(np.min(w.grid.geodesic_from_field(w.grid.distance_field(pos), goals)))
                    rows.append((u.episode.category, i, 10 * math.log10(np.mean([v[1] for v in win]) + 1e-20), path))
                    win = []
    finally:
        env.close()
    return rows


def fit_drive(episodes: int = 80, seed: int = 7, split: str = "train", window: int | None = None) -> dict:
    """:data:`DRIVE_FIT` from ``episodes`` episodes of ``split`` (:func:`drive_rows` with windows of ``window`` steps,
    default ``GanAgent.WINDOW``; training homes only): least squares of ln(path + ``GanAgent.NEAR``) - the
    category's offset in LEVEL_FIT on the level. Returns the fit, its residual standard deviation and the part of it
    within an episode (``resid``, ``within``: ln units)."""
    from agents.semnav import LEVEL_FIT

    rows = drive_rows(episodes, seed, split, int(window or GanAgent.WINDOW))
    db = np.array([r[2] for r in rows])
    y = np.log(np.array([r[3] for r in rows]) + GanAgent.NEAR) - np.array([LEVEL_FIT["offset"][r[0]] for r in rows])
    coef = np.linalg.lstsq(np.c_[db, np.ones_like(db)], y, rcond=None)[0]
    res = y - coef[0] * db - coef[1]
    ep = np.array([r[1] for r in rows])
    within = np.concatenate([res[ep == e] - res[ep == e].mean() for e in np.unique(ep)])
    return {"slope": round(float(coef[0]), 4), "shift": round(float(coef[1]), 3), "resid": round(float(res.std()), 3),
            "within": round(float(within.std()), 3), "windows": len(rows), "episodes": episodes}


class GanAgent(MapAgent):
    """See the module's docstring."""

    name = "gan"
    POST_CELL = 0.2  # m: the cells of the goal's probability grid
    WINDOW = 16  # audible steps per level heard while driving
    SIGMA_SHARED = 0.3  # ln units: the error the levels of one episode share
    SIGMA_SPIN = 0.25  # ln units: a spin's own error (with the shared: the fit's 0.39)
    SIGMA_DRIVE = 0.4  # ln units: a driving window's own error (0.27 measured; successive ones are not independent)
    NEAR = 1.0  # m: the goal sounds from about this far beyond where to stop (the levels read ln(path + NEAR))
    KAPPA = 1.2  # von Mises concentration of a spin's bearing (median error about 45 degrees)
    ARRIVE = 0.2  # m from the estimate: arrived
    SETTLE = 0.6  # m: after a spin there, an estimate within this of the robot stops it
    MAX_SPINS = 4
    REPLAN = 10  # steps between re-planning
    STUCK = 40  # steps without coming 0.1 m nearer the estimate: treat as arrived
    QUIET = 5  # silent steps: the sound has stopped

    def env_kwargs(self) -> dict:
        return {"sensors": ("depth", "spectrogram", "audio", "pose", "bump")}

    def reset(self, env, obs, info):
        missing = [k for k in ("audio", "spectrogram", "pose") if k not in obs]
        if missing:
            from sonicverse_core.errors import ConfigError

            raise ConfigError(f"gan needs the env's {', '.join(repr(k) for k in missing)} sensor"
                              f"{'s' if len(missing) > 1 else ''} (env_kwargs() lists what it reads)")
        super().reset(env, obs, info)
        from agents.navmap import SoundNamer

        self.ears = SoundNamer()
        self.sr = env.cfg.sample_rate
        self.max_steps = int(env.cfg.max_steps)
        self.steps = 0
        self.full_turn = turn_steps(self.robot, self.dt)
        n = int(round(self.SIZE * self.CELL / self.POST_CELL))
        self.n = n
        self.f = int(round(self.POST_CELL / self.CELL))  # map cells per grid cell
        c = (np.arange(n) - n / 2 + 0.5) * self.POST_CELL
        self._gx, self._gy = np.meshgrid(c, c, indexing="ij")
        self.levels: list[tuple[np.ndarray, float, bool, np.ndarray]] = []  # (place, dB, from a spin, ln(distance+1))
        self.bearings: list[tuple[np.ndarray, float]] = []  # (place, world bearing rad)
        self.ruled_out = np.zeros((n, n), bool)  # AudioGoal: stood there and the episode went on
        self.quiet = 0
        self.window: list[tuple[np.ndarray, float]] = []  # (place, mean square) per audible step
        self.spins = 0
        self._start_spin()
        self.goal, self.path, self.k, self.since_plan = None, None, 0, self.REPLAN
        self.closest, self.no_closer = math.inf, 0
        self.backoff = 0
        self.trace: list[dict] = []  # what it heard and estimated (for analysis and tests)
        self._turn = _wheels(0.0, math.radians(self.robot.max_turn_deg), self.robot)  # on the spot, to the left
        self._evidence = None  # (what it was computed from, the levels' and bearings' log-likelihood per cell)

    # --- hearing ----------------------------------------------------------------------------------------------
    def _start_spin(self) -> None:
        self.spin_left = self.full_turn
        self.turn: list[tuple[float, float]] = []  # (yaw rad, ILD dB) of the spin's audible steps
        self.spin_e: list[float] = []

    def _hear(self, obs, p, yaw) -> None:
        from agents.semnav import ild

        audio = np.asarray(obs["audio"], float)
        e = float(np.mean(audio * audio))
        if 0 < self.spin_left <= self.full_turn - 3:  # the turn's steps 3.., as LEVEL_FIT was fitted (spin_level)
            self.spin_e.append(e)
        if not self.ears.hear(obs["spectrogram"]):
            self.quiet += 1
            self.window = []
            return
        self.quiet = 0
        if self.spin_left > 0:
            self.turn.append((math.radians(yaw), ild(audio, self.sr)))
            return
        self.window.append((p.copy(), e))
        if len(self.window) >= self.WINDOW:
            pos = np.mean([w[0] for w in self.window], axis=0)
            self.add_level(pos, 10 * math.log10(np.mean([w[1] for w in self.window]) + 1e-20), False)
            self.window = []

    def _end_spin(self, p) -> None:
        from agents.semnav import fit_bearing

        self.spins += 1
        b = fit_bearing(self.turn)
        if b is not None:
            self.bearings.append((np.array(p, float), b))
        if len(self.spin_e) >= 5:
            self.add_level(np.array(p, float), 10 * math.log10(np.mean(self.spin_e) + 1e-20), True)

    def _coarse_occ(self) -> np.ndarray:
        """The grid's cells holding a mapped obstacle."""
        return (self.occ >= 2).reshape(self.n, self.f, self.n, self.f).any(axis=(1, 3))

    def add_level(self, pos, db: float, spin: bool) -> None:
        """A level heard at ``pos``, with the path distance from there to every grid cell (the map as it is)."""
        from scipy.ndimage import binary_dilation

        occ = self._coarse_occ()
        blocked = binary_dilation(occ) if occ.any() else occ
        s = np.clip(np.floor(np.asarray(pos) / self.POST_CELL).astype(int) + self.n // 2, 0, self.n - 1)
        blocked[s[0], s[1]] = False
        dist = grid_field(blocked, s)[0].reshape(self.n, self.n) * self.POST_CELL
        straight = np.hypot(self._gx - pos[0], self._gy - pos[1])
        dist = np.where(np.isfinite(dist), dist, 1.5 * straight)  # behind mapped walls: a detour
        self.levels.append((np.array(pos, float), float(db), spin, np.log(dist + self.NEAR)))

    # --- estimating -------------------------------------------------------------------------------------------
    def log_posterior(self) -> np.ndarray | None:
        """The log-probability (unnormalised) of each grid cell being where to stop for the goal; None before a
        level and a category are known. The evidence is recomputed only when a level, a bearing or the category is
        new; the mask of mapped obstacles and ruled-out cells every call."""
        k = self.ears.category()
        if k < 0 or not self.levels:
            return None
        key = (k, len(self.levels), len(self.bearings))
        if self._evidence is None or self._evidence[0] != key:
            self._evidence = (key, self._log_evidence(k))
        return np.where(self._coarse_occ() | self.ruled_out, -np.inf, self._evidence[1])

    def _log_evidence(self, k: int) -> np.ndarray:
        """The levels' and the bearings' log-likelihood per grid cell, for category ``k``."""
        from agents.semnav import LEVEL_FIT
        from assets_manifest.soundbank import CATEGORIES

        slope, off = LEVEL_FIT["slope"], LEVEL_FIT["offset"][CATEGORIES[k]]
        res, w = [], []
        for _, db, spin, lnd in self.levels:  # r_i = ln(d_i(cell) + NEAR) - predicted_i
            if spin:
                w.append(1.0 / self.SIGMA_SPIN ** 2)
                res.append(lnd - math.log(math.exp(slope * db + off) + self.NEAR))
            else:
                w.append(1.0 / self.SIGMA_DRIVE ** 2)
                res.append(lnd - (DRIVE_FIT["slope"] * db + off + DRIVE_FIT["shift"]))
        lp = shared_error_loglik(res, w, self.SIGMA_SHARED)
        for pos, b in self.bearings:
            lp = lp + self.KAPPA * np.cos(np.arctan2(self._gy - pos[1], self._gx - pos[0]) - b)
        return lp

    def estimate(self) -> np.ndarray | None:
        lp = self.log_posterior()
        if lp is None or not np.isfinite(lp).any():
            return None
        i, j = np.unravel_index(int(np.argmax(lp)), lp.shape)
        return np.array([self._gx[i, j], self._gy[i, j]])

    # --- acting -----------------------------------------------------------------------------------------------
    def _plan(self, p, goal) -> None:
        s, _, dist, pred = self._reachable(p, 2)
        g = np.clip(self._cell(goal), 0, self.SIZE - 1)
        if not np.isfinite(dist[g[0], g[1]]):  # the goal cell is blocked or cut off: the reachable cell nearest it
            reach = np.argwhere(np.isfinite(dist))
            g = reach[int(np.argmin(np.hypot(*(reach - g).T)))] if len(reach) else s
        cells = grid_trace(pred, self.SIZE, s, g)
        self.path = (np.array(cells, float) - self.SIZE // 2 + 0.5) * self.CELL if cells else np.array([p])
        self.k = min(2, len(self.path) - 1)
        self.since_plan = 0

    def act(self, obs, info):
        p, yaw = self._pose(obs)
        if not (np.isfinite(p).all() and math.isfinite(yaw)):
            from sonicverse_core.errors import ConfigError

            raise ConfigError(f"gan needs a finite pose, got {obs['pose']}")
        if "depth" in obs:
            map_depth(self.occ, np.asarray(obs["depth"])[..., 0], p, yaw, self._fx, self.robot.camera_height,
                      self.CELL)
        self._hear(obs, p, yaw)
        self.steps += 1
        if self.stop_dim and self.steps >= self.max_steps:
            return self._out([0.0, 0.0], stop=True)
        turn = self._turn
        if self.spin_left > 0:
            self.spin_left -= 1
            if self.spin_left == 0:
                self._end_spin(p)
                est = self.estimate()
                self.trace.append({"step": self.steps, "spin": self.spins, "at": p.tolist(),
                                   "estimate": None if est is None else est.tolist()})
                if (est is not None and self.spins > 1 and self.stop_dim
                        and np.linalg.norm(est - p) < self.SETTLE):
                    return self._out([0.0, 0.0], stop=True)
                self.since_plan = self.REPLAN
            return self._out(turn)
        est = self.estimate()
        if est is None:  # nothing heard yet: keep turning
            return self._out(turn)
        if obs.get("bump") is not None and obs["bump"][0] > 0:
            self.backoff, self.since_plan = 3, self.REPLAN
        if self.backoff > 0:
            self.backoff -= 1
            return self._out(_wheels(-0.3 * self.robot.max_speed, 0.0, self.robot))
        if self.goal is None or np.linalg.norm(est - self.goal) > 0.3:
            self.goal, self.since_plan = est, self.REPLAN
            self.closest, self.no_closer = math.inf, 0
        self.since_plan += 1
        if self.path is None or self.since_plan >= self.REPLAN:
            self._plan(p, self.goal)
        dist = float(np.linalg.norm(self.goal - p))
        if dist < self.closest - 0.1:
            self.closest, self.no_closer = dist, 0
        else:
            self.no_closer += 1
        end = self.path[-1]
        if dist < self.ARRIVE or self.no_closer >= self.STUCK or (
                np.linalg.norm(end - p) < 0.15 and np.linalg.norm(end - self.goal) > self.ARRIVE):
            return self._arrived(p)
        while self.k < len(self.path) - 1 and np.linalg.norm(self.path[self.k] - p) < 0.2:
            self.k += 1
        return self._out(_pursue(p, yaw, self.path[self.k], self.robot, self.dt, slow_within=0.3))

    def _arrived(self, p):
        """At the estimate (or as near as the map lets it come)."""
        if self.stop_dim:
            if self.quiet >= self.QUIET or self.spins >= self.MAX_SPINS:
                return self._out([0.0, 0.0], stop=True)
            self._start_spin()  # still sounding: listen here once more
            return self._out(self._turn)
        # no stop action (AudioGoal ends on arrival): not here; listen again while it sounds
        i, j = np.clip(np.floor(p / self.POST_CELL).astype(int) + self.n // 2, 0, self.n - 1)
        self.ruled_out[max(0, i - 1):i + 2, max(0, j - 1):j + 2] = True
        self.goal, self.closest, self.no_closer = None, math.inf, 0
        if self.spins < self.MAX_SPINS and self.quiet < self.QUIET:
            self._start_spin()
        return self._out(self._turn)
