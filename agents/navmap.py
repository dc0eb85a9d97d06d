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

import numpy as np

from agents.scripted import ego_offsets, map_depth


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
