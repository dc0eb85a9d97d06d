"""What a learned navigator reads of where it has been (``sonicverse train --map`` on AudioGoal and
SemanticAudioNav; ``AVNavConfig.map_kind == "nav"``): a map the robot builds from its own sensors as it drives, drawn
as an egocentric image like :class:`agents.following.EgoMap`'s.

A navigation task gives no floor plan, and one step of a steady sound says little about where it plays (the sound
localiser's bearing is at chance in these homes: ``agents/checkpoints/sound-localizer.md``). What does say where the
sound is, is how loud it was at the places the robot has been: a second of sound is louder nearer its room. The
policy's GRU could keep that in mind; this map keeps it where it was heard. Nothing here is privileged: depth,
the spectrogram and the odometry pose are the policy's own inputs.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from agents.scripted import draw_route, ego_offsets, grid_cells, map_depth, project_depth


class NavEgoMap:
    """An egocentric image of ``SIZE`` x ``SIZE`` pixels of ``RES`` m, the robot at the centre facing the top (its
    left to the left), uint8 channels:

    0. obstacles the depth camera has seen (points 0.08-0.6 m above the floor, two hits or more in a pixel);
    1. floor the depth camera has seen;
    2. how loud the sound was where the robot stood (the spectrogram's second, in dB, averaged per pixel; the
       loudest place so far at 255, 40 dB below it or less at 1, never visited at 0);
    3. the robot's track, fading over ``TRACK_S`` s.

    The world map behind it covers ``WORLD`` m x ``WORLD`` m around the start (odometry frame)."""

    SIZE, RES = 32, 0.25
    CHANNELS = 4
    WORLD = 40.0
    TRACK_S = 30.0
    RANGE_DB = 40.0

    def reset(self, env, obs, info) -> None:
        n = int(round(self.WORLD / self.RES))
        self.n = n
        self.occ = np.zeros((n, n), np.int16)
        self.floor = np.zeros((n, n), bool)
        self.level_sum = np.zeros((n, n))
        self.level_n = np.zeros((n, n), np.int32)
        self.track = np.full((n, n), -np.inf)
        self.t = 0.0
        self.dt = env.cfg.step_seconds
        self.camera_height = env.robot.camera_height
        self.fx = (env.cfg.width / 2) / math.tan(math.radians(env.cfg.hfov) / 2)
        self._fwd, self._left = ego_offsets(self.SIZE, self.RES)
        self.image = np.zeros((self.CHANNELS, self.SIZE, self.SIZE), np.uint8)

    def _cell(self, xy) -> np.ndarray:
        return np.floor(np.asarray(xy, float) / self.RES).astype(int) + self.n // 2

    def observe(self, obs, info) -> np.ndarray:
        """Add this step's observation to the map and return the image (C, H, W) uint8 (the same array each step:
        copy it to keep it)."""
        x, y, s, c = (float(v) for v in obs["pose"])
        p, yaw = np.array([x, y]), math.degrees(math.atan2(s, c))
        if not (np.isfinite(p).all() and math.isfinite(yaw)):
            from sonicverse_core.errors import ConfigError

            raise ConfigError(f"the map needs a finite pose, got {obs['pose']}")
        if "depth" in obs:
            map_depth(self.occ, np.asarray(obs["depth"])[..., 0], p, yaw, self.fx, self.camera_height, self.RES,
                      floor=self.floor)
        self.p, self.yaw = p, yaw  # this step's odometry pose (subclasses draw from it)
        i, j = self._cell(p)
        inside = 0 <= i < self.n and 0 <= j < self.n
        if inside:
            if "spectrogram" in obs:
                e = np.expm1(np.asarray(obs["spectrogram"], np.float64))
                self.level_sum[i, j] += 10.0 * math.log10(float(np.mean(e * e)) + 1e-12)
                self.level_n[i, j] += 1
            self.track[i, j] = self.t
        self.t += self.dt
        # the egocentric window
        a = math.radians(yaw)
        ca, sa = math.cos(a), math.sin(a)
        wx, wy = x + ca * self._fwd - sa * self._left, y + sa * self._fwd + ca * self._left
        idx = self._cell(np.stack([wx.ravel(), wy.ravel()], 1))
        ok = (idx >= 0).all(1) & (idx < self.n).all(1)
        r, q = np.clip(idx[:, 0], 0, self.n - 1), np.clip(idx[:, 1], 0, self.n - 1)
        self._window = (r, q, ok)  # the world cells under the image's pixels (SemNavMap draws its channel there)
        img = self.image
        shape = (self.SIZE, self.SIZE)
        img[0] = ((self.occ[r, q] >= 2) & ok).reshape(shape) * np.uint8(255)
        img[1] = (self.floor[r, q] & ok).reshape(shape) * np.uint8(255)
        heard = self.level_n > 0
        img[2] = 0
        if heard.any():
            mean = np.where(heard, self.level_sum / np.maximum(self.level_n, 1), -np.inf)
            top = float(mean[heard].max())
            v = mean[r, q]
            rel = np.clip(1.0 + (v - top) / self.RANGE_DB, 0.0, 1.0)
            px = np.where(np.isfinite(v) & ok, np.round(1 + 254 * rel), 0)
            img[2] = px.reshape(shape).astype(np.uint8)
        age = self.t - self.track[r, q]
        img[3] = np.round(255 * np.clip(1.0 - age / self.TRACK_S, 0.0, 1.0) * ok).reshape(shape).astype(np.uint8)
        return img


#: the sound classifier :class:`SemNavMap` names a goal's category with: the shipped SAVi's goal predictor
CLASSIFIER = Path(__file__).resolve().parent / "checkpoints" / "savi_AudioGoal.pt"
_classifier: dict = {}


def sound_classifier(path=CLASSIFIER):
    """``f(spectrogram) -> log-probabilities over assets_manifest.soundbank.CATEGORIES`` from a SAVi checkpoint's goal
    predictor (its spectrogram CNN and category head; loaded once per process and path, frozen)."""
    import torch

    key = str(path)
    if key not in _classifier:
        from agents.models import SPEC_MAX, acting_threads
        from agents.savi import load

        model, _ = load(path, "savi")
        model.eval()
        if model.category is None:
            from sonicverse_core.errors import ConfigError

            raise ConfigError(f"{path} has no category head to name a sound with")
        net, head = model.goal_net, model.category

        def classify(spec) -> np.ndarray:
            # quantised as the policies see it (agents.imitation._quantise), then the predictor's own scaling
            q = np.clip(np.round(np.asarray(spec, np.float32) / SPEC_MAX * 255), 0, 255) * (1.0 / 255)
            with torch.no_grad(), acting_threads():
                x = torch.from_numpy(q.astype(np.float32))[None]
                return torch.log_softmax(head(net(x)).double(), -1)[0].numpy()

        _classifier[key] = classify
    return _classifier[key]


def category_bits() -> tuple[np.ndarray, np.ndarray]:
    """(bit, lut): each sound category's bit in a sightings grid (its camera class id), and per camera class id its
    category's bit mask (0: not one of the categories), for :func:`map_semantic`."""
    from assets_manifest.soundbank import CATEGORIES
    from sonicverse_core.sensors.camera import CLASSES

    bit = np.array([CLASSES.index(c) for c in CATEGORIES], np.int64)
    lut = np.zeros(len(CLASSES), np.int64)
    lut[bit] = np.int64(1) << bit
    return bit, lut


class SoundNamer:
    """Which category sounds: while the goal is heard (the spectrogram's mean above ``agents.savi.AUDIBLE``) the
    goal predictor (:func:`sound_classifier`) scores the categories, and the scores add up as log-likelihoods."""

    def __init__(self):
        from assets_manifest.soundbank import CATEGORIES

        self.score = np.zeros(len(CATEGORIES))
        self.heard = 0
        self.classify = sound_classifier()

    def hear(self, spec) -> bool:
        """Score one step's spectrogram if the goal is heard in it; whether it was."""
        from agents.savi import AUDIBLE

        spec = np.asarray(spec)
        if float(spec.mean()) <= AUDIBLE:
            return False
        self.score += self.classify(spec)
        self.heard += 1
        return True

    def category(self, min_heard: int = 1) -> int:
        """The index (into CATEGORIES) of the category named so far; -1 before ``min_heard`` audible steps."""
        return int(np.argmax(self.score)) if self.heard >= min_heard else -1


class SemNavMap(NavEgoMap):
    """:class:`NavEgoMap` with a fifth channel for SemanticAudioNav (``train --map`` there; ``map_kind`` "sem"):

    4. where the semantic camera has seen an object of the category the robot's ears name (255), else 0: every
       object of that category (the episode's target is one of them, the one that sounded).

    The category is the robot's own estimate: while the goal sounds (the spectrogram's mean above
    ``agents.savi.AUDIBLE``), the shipped SAVi's goal predictor (:func:`sound_classifier`, trained on AudioGoal's heard
    sounds in train homes) scores the 15 categories each step; the scores add up as log-likelihoods, and the channel
    shows the best one's sightings (empty until something is heard). It keeps the estimate after the sound stops.
    Sightings: every second pixel of the semantic image whose category is one of the 15, projected with its depth
    (any height) into the world grid, a bit per category per cell. The camera's category ids are ground truth (the
    scene's labels, as Habitat's semantic sensor), a stand-in for an object detector on RGB: what the paper's agents
    learn from RGB, this map is told.

    With ``teach`` set (``train --teacher scripted``) sem-nav (``teacher_class()``: :class:`agents.semnav.SemNavAgent`)
    acts on the same observations each step; its action (``action``) is the imitation label."""

    CHANNELS = 5
    teach = False

    @staticmethod
    def teacher_class():
        """The sem-nav this map runs with ``teach`` (the current one)."""
        from agents.semnav import SemNavAgent

        return SemNavAgent

    def reset(self, env, obs, info) -> None:
        super().reset(env, obs, info)
        self.bit, self.lut = category_bits()
        self.seen = np.zeros((self.n, self.n), np.int64)
        self.action = None
        if self.teach:  # train --teacher scripted: sem-nav acts on the same observations (seeded by the episode)
            import zlib

            seed = zlib.crc32(str(env.unwrapped.episode.episode_id).encode())
            self.teacher = self.teacher_class()(np.random.default_rng(seed))
            self.teacher.reset(env, obs, info)
            self.ears = self.teacher.ears  # its ears name the sound for both (one classification a step)
        else:
            self.ears = SoundNamer()

    def category(self) -> int:
        """The index (into CATEGORIES) of the category the ears name so far, -1 before anything was heard."""
        return self.ears.category()

    def observe(self, obs, info) -> np.ndarray:
        if "semantic" not in obs:
            from sonicverse_core.errors import ConfigError

            raise ConfigError("the semantic map needs the env's 'semantic' sensor")
        img = super().observe(obs, info)
        if self.teach:
            self.action = self.teacher.act(obs, info)  # the label (``ego.action``), not taken here; it hears too
        else:
            self.ears.hear(obs["spectrogram"])
        if "depth" in obs:
            map_semantic(self.seen, np.asarray(obs["depth"])[..., 0], np.asarray(obs["semantic"])[..., 0], self.lut,
                         self.p, self.yaw, self.fx, self.RES)
        k = self.category()
        r, q, ok = self._window
        if k < 0:
            img[4] = 0
        else:
            hit = ((self.seen[r, q] >> self.bit[k]) & 1).astype(bool) & ok
            img[4] = hit.reshape(self.SIZE, self.SIZE) * np.uint8(255)
        return img


class RouteNavMap(SemNavMap):
    """:class:`SemNavMap` with a sixth channel, the way sem-nav would go now (``train --map route`` on AudioGoal and
    SemanticAudioNav; ``map_kind`` "route2", or "route" for the files trained before session 56), as
    :class:`agents.following.EgoMap` draws the scripted follower's:

    5. sem-nav's route from the robot, at 255 to a sighting of the named category it would stop beside, at 128 to
       the frontier it would explore; while it would turn to face the sighting, the line from the robot to it at
       255; empty while it turns on the spot to hear the sound first.

    sem-nav runs on the robot's own observations every step (as the follower's map runs the scripted follower), so
    this map is as privileged as sem-nav: the semantic camera's ground-truth category ids, nothing else. With
    ``train --teacher scripted`` its action is also the label, so the policy learns actions its map explains.

    Which sem-nav draws it is part of what a policy learnt to read, so it is kept per ``map_kind``: this class
    (kind "route") runs :class:`agents.semnav.RouteTeacher`, sem-nav before session 55's way out of pockets, which
    the shipped files of sessions 44-53 were measured with; :class:`RouteNavMap2` (kind "route2", what ``train
    --map route`` trains now) runs the current :class:`agents.semnav.SemNavAgent`."""

    CHANNELS = 6
    teach = True  # sem-nav acts every step, to draw its route (its action is the label only with --teacher scripted)
    #: m: the route's sem-nav counts itself arrived (and draws the line to face its target, which opens the stop gate)
    #: once the robot is this close to the target (:attr:`agents.semnav.SemNavAgent.BESIDE_M`; session 70), as the
    #: policies play and as DAgger labels (a learner that drives up beside the target is told to face it and stop);
    #: None: only on its approach cell
    BESIDE_M = 0.3

    @staticmethod
    def teacher_class():
        """The sem-nav that draws the route: as the "route" files learnt it."""
        from agents.semnav import RouteTeacher

        return RouteTeacher

    def reset(self, env, obs, info) -> None:
        super().reset(env, obs, info)
        self.teacher.BESIDE_M = self.BESIDE_M

    def observe(self, obs, info) -> np.ndarray:
        img = super().observe(obs, info)
        img[5] = 0
        t = self.teacher
        p, yaw = self.p, self.yaw
        if t.mode == "face" and t.target is not None:
            cells = t.target[1]
            draw_route(img[5], p, yaw, [p, cells[int(np.argmin(np.linalg.norm(cells - p, axis=1)))]], self.RES)
        elif t.mode in ("explore", "approach") and t.path is not None and len(t.path) > 0:
            draw_route(img[5], p, yaw, np.vstack([p[None], t.path[min(t.k, len(t.path) - 1):]]), self.RES,
                       255 if t.mode == "approach" else 128)
        return img


class RouteNavMap2(RouteNavMap):
    """:class:`RouteNavMap` whose route the current :class:`agents.semnav.SemNavAgent` draws (``map_kind`` "route2":
    ``train --map route`` since session 56)."""

    teacher_class = staticmethod(SemNavMap.teacher_class)


def map_semantic(seen: np.ndarray, depth: np.ndarray, sem: np.ndarray, lut: np.ndarray, p, yaw: float, fx: float,
                 cell: float, stride: int = 2) -> None:
    """OR each category's bit (``lut[class id]``) into the cells of ``seen`` (cells of ``cell`` m centred on the
    odometry origin) where every ``stride``-th pixel of the semantic image ``sem`` lands, by its ``depth``, seen from
    pose ``p`` (x, y), ``yaw`` degrees (as :func:`agents.scripted.map_depth`)."""
    rows, cols, z, _, wx, wy = project_depth(depth, p, yaw, fx, stride)
    bits = lut[np.clip(sem[np.ix_(rows, cols)], 0, len(lut) - 1)]
    ok = (z > 0.1) & (bits != 0)
    if np.any(ok):
        r, c, good = grid_cells(wx[ok], wy[ok], cell, seen.shape[0])
        np.bitwise_or.at(seen, (r, c), bits[ok][good])
