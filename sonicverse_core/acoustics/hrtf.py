"""HRTF interpolation.

Each HRIR is split into an onset delay per ear (the interaural time difference lives there) and an onset-aligned
filter that keeps ``PRE`` samples before the onset. Directions are interpolated barycentrically over the convex hull
triangulation of the measured directions: aligned filters are mixed linearly (no comb filtering, since onsets are
aligned) and onset delays are mixed linearly and applied as fractional delays by the renderer. The set is resampled
to the engine rate and truncated to ``taps``.
"""
from __future__ import annotations

import numpy as np
from scipy.signal import resample_poly
from scipy.spatial import ConvexHull

from sonicverse_core.errors import ConfigError

PRE = 16  # samples kept before the onset: room for the pre-ringing of band filters


class HrtfInterpolator:
    """directions (n, 3) unit vectors (head frame: x fwd, y left, z up), filters (n, 2, taps) float32 aligned,
    onsets (n, 2) float seconds."""

    def __init__(self, hrir_set, sample_rate: int, taps: int = 256):
        sr0 = hrir_set.sample_rate
        h = np.asarray(hrir_set.hrirs, np.float64)
        if sr0 != sample_rate:
            g = np.gcd(int(sr0), int(sample_rate))
            h = resample_poly(h, sample_rate // g, sr0 // g, axis=-1)
        self.sample_rate = sample_rate
        self.name = hrir_set.name
        peak = np.max(np.abs(h), axis=-1, keepdims=True)
        onset = np.argmax(np.abs(h) >= 0.1 * np.maximum(peak, 1e-12), axis=-1)  # (n, 2) samples, -20 dB
        start = np.maximum(onset - PRE, 0)
        n, _, L = h.shape
        idx = start[..., None] + np.arange(taps)[None, None, :]
        aligned = np.where(idx < L, np.take_along_axis(h, np.minimum(idx, L - 1), axis=-1), 0.0)
        # equalise so that the frontal direction has unit energy on average across ears
        self.directions = np.asarray(hrir_set.directions, np.float64)
        front = int(np.argmax(self.directions @ np.array([1.0, 0.0, 0.0])))
        norm = np.sqrt(np.mean(np.sum(aligned[front] ** 2, axis=-1)))
        self.filters = (aligned / max(norm, 1e-12)).astype(np.float32)
        self.onsets = start / sample_rate  # seconds (the PRE samples are part of the filter)
        self.taps = taps
        hull = ConvexHull(self.directions)
        self._tri = hull.simplices
        # inverse of each triangle's vertex matrix for barycentric weights
        self._inv = np.linalg.inv(self.directions[self._tri].transpose(0, 2, 1))
        self._centroid = self.directions[self._tri].mean(1)
        self._centroid /= np.linalg.norm(self._centroid, axis=1, keepdims=True)

    def weights(self, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For unit vectors (m, 3): vertex indices (m, 3) and barycentric weights (m, 3) summing to 1."""
        d = np.atleast_2d(directions)
        if not np.all(np.isfinite(d)):
            raise ConfigError("HRTF directions must be finite")
        nrm = np.linalg.norm(d, axis=1, keepdims=True)
        d = np.where(nrm > 1e-12, d / np.maximum(nrm, 1e-12), np.array([1.0, 0, 0]))
        # candidate triangles: the 8 whose centroids are nearest, pick the one with all weights >= 0
        cand = np.argpartition(-(d @ self._centroid.T), 8, axis=1)[:, :8]
        w = np.einsum("mkij,mj->mki", self._inv[cand], d)  # (m, 8, 3)
        ok = np.all(w >= -1e-9, axis=2)
        pick = np.where(ok.any(1), np.argmax(ok, axis=1), np.argmax(w.min(2), axis=1))
        tri = self._tri[cand[np.arange(len(d)), pick]]
        ww = np.clip(w[np.arange(len(d)), pick], 0, None)
        ww /= np.maximum(ww.sum(1, keepdims=True), 1e-12)
        return tri, ww

    def lookup(self, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Interpolated aligned filters (m, 2, taps) and onset delays (m, 2) seconds for unit vectors (m, 3)."""
        tri, w = self.weights(directions)
        f = np.einsum("mk,mket->met", w, self.filters[tri])
        o = np.einsum("mk,mke->me", w, self.onsets[tri])
        return f, o

    def nearest(self, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest-neighbour lookup (the cheap, clicky alternative used in accuracy sweeps)."""
        i = np.argmax(np.atleast_2d(directions) @ self.directions.T, axis=1)
        return self.filters[i], self.onsets[i]
