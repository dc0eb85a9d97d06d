"""HRTF interpolation.

Each HRIR is split into an onset delay per ear (the interaural time difference lives there) and an onset-aligned
filter that keeps ``PRE`` samples before the onset. Directions are interpolated barycentrically over the convex hull
triangulation of the measured directions: aligned filters are mixed linearly (no comb filtering, since onsets are
aligned) and onset delays are mixed linearly and applied as fractional delays by the renderer. The set is resampled
to the engine rate and truncated to ``taps``.
"""
from __future__ import annotations

from functools import cached_property

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
        hull = self._complete_sphere()
        try:
            hull = hull or ConvexHull(self.directions)
        except Exception as exc:  # noqa: BLE001 - scipy's QhullError: a degenerate layout
            from sonicverse_core.errors import AssetError

            raise AssetError(f"HRTF set '{self.name}': its {len(self.directions)} directions do not span a sphere "
                             f"({str(exc).splitlines()[0]})") from None
        self._tri = hull.simplices.astype(np.int64)
        # inverse of each triangle's vertex matrix for barycentric weights
        self._inv = np.linalg.inv(self.directions[self._tri].transpose(0, 2, 1))
        self._centroid = self.directions[self._tri].mean(1)
        self._centroid /= np.linalg.norm(self._centroid, axis=1, keepdims=True)

    @cached_property
    def diffuse_field(self) -> tuple[np.ndarray, np.ndarray]:
        """Per band of ``BANDS``: the diffuse-field amplitude gain of each ear (2, 9) (the power average over all
        measured directions, on the same scale as the direct path's filters) and the diffuse-field interaural
        coherence (9,) |sum_dirs H_L H_R*| / sqrt(sum |H_L|^2 sum |H_R|^2), averaged over the band's bins, with the
        interaural delays (the onsets) included: near 1 at low frequencies, falling towards 0 above about 1 kHz.
        What the late tail is coloured and decorrelated with; computed once per set."""
        from sonicverse_core.scene.materials import BANDS

        fs = self.sample_rate
        n = 1 << int(np.ceil(np.log2(max(4096, 2 * self.taps))))
        f = np.fft.rfftfreq(n, 1 / fs)
        H = np.fft.rfft(self.filters.astype(np.float64), n, axis=-1)  # (dirs, 2, F)
        H = H * np.exp(-2j * np.pi * f[None, None, :] * self.onsets[:, :, None])
        power = np.mean(np.abs(H) ** 2, axis=0)  # (2, F)
        cross = np.abs(np.sum(H[:, 0] * np.conj(H[:, 1]), axis=0))
        coh = cross / np.sqrt(np.maximum(np.sum(np.abs(H[:, 0]) ** 2, 0) * np.sum(np.abs(H[:, 1]) ** 2, 0), 1e-300))
        gains, coherence = np.ones((2, len(BANDS))), np.ones(len(BANDS))
        for b, fc in enumerate(BANDS):
            sel = (f >= fc / np.sqrt(2)) & (f < fc * np.sqrt(2))
            if sel.any():
                gains[:, b] = np.sqrt(power[:, sel].mean(axis=1))
                coherence[b] = float(np.clip(coh[sel].mean(), 0.0, 1.0))
            elif b:  # a band above the Nyquist frequency: as the one below
                gains[:, b], coherence[b] = gains[:, b - 1], coherence[b - 1]
        return gains, coherence

    def _complete_sphere(self):
        """Sets that do not surround the head get virtual directions, each the mean of the aligned filters and
        onsets (no interaural difference, as for a source straight above or below): a set measured in one plane
        (the horizontal ring, a common SOFA layout) gets the two poles of that plane; a set on one side of a plane
        through the head (no measurement below the horizon) gets the pole of the empty side, so every direction
        falls in a triangle that does not pass through the head's centre. Fewer than 3 directions are refused.
        Returns the hull when the set already surrounds the head (nothing added), else None."""
        from sonicverse_core.errors import AssetError

        d = self.directions
        if len(d) < 3:
            raise AssetError(f"HRTF set '{self.name}' has {len(d)} directions; at least 3 are needed")
        _, sv, vt = np.linalg.svd(d, full_matrices=False)
        if sv[-1] < 1e-3 * sv[0]:  # all in one plane through the centre
            poles = np.stack([vt[-1], -vt[-1]])
        else:
            try:
                hull = ConvexHull(d)
            except Exception:  # noqa: BLE001 - refused by the caller's hull
                return None
            eq = hull.equations  # outward normals n and offsets c: n.x + c = 0 on a facet
            if eq[:, 3].max() < -0.05:
                return hull  # the centre is well inside: nothing to add
            far = eq[np.argmax(eq[:, 3]), :3]  # the facet nearest the centre faces the empty side
            poles = far[None] / np.linalg.norm(far)
        mean_f = self.filters.mean(0, keepdims=True)
        self.directions = np.concatenate([d, poles])
        self.filters = np.concatenate([self.filters, np.repeat(mean_f, len(poles), 0)]).astype(np.float32)
        self.onsets = np.concatenate([self.onsets, np.full((len(poles), 2), float(self.onsets.mean()))])
        return None

    def _exact_triangles(self, d: np.ndarray) -> np.ndarray:
        out = np.empty(len(d), np.int64)
        for i in range(0, len(d), 4096):
            chunk = d[i:i + 4096]
            k = min(8, len(self._tri) - 1)  # a sparse set has few triangles
            cand = np.argpartition(-(chunk @ self._centroid.T), k, axis=1)[:, :k + 1]
            w = np.einsum("mkij,mj->mki", self._inv[cand], chunk)
            ok = np.all(w >= -1e-9, axis=2)
            pick = np.where(ok.any(1), np.argmax(ok, axis=1), np.argmax(w.min(2), axis=1))
            out[i:i + 4096] = cand[np.arange(len(chunk)), pick]
            miss = np.flatnonzero(~ok.any(1))  # big triangles (the open bottom cap): search them all
            if len(miss):
                wa = np.einsum("tij,mj->mti", self._inv, chunk[miss]).min(2)
                out[i + miss] = np.argmax(wa, axis=1)
        return out

    def _grid(self) -> tuple[np.ndarray, float]:
        """A 2-degree azimuth/elevation table: per cell, the triangles holding its centre and its four corners
        (na, ne, 5): candidates for the compiled lookup."""
        if getattr(self, "_grid_tri", None) is None:
            step = 2.0

            def dirs(az_deg, el_deg):
                A, E = np.meshgrid(np.radians(az_deg), np.radians(el_deg), indexing="ij")
                return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1)

            centres = dirs(np.arange(-180, 180, step) + step / 2, np.arange(-90, 90, step) + step / 2)
            corners = dirs(np.arange(-180, 180 + step, step), np.arange(-90, 90 + step, step))
            na, ne = centres.shape[:2]
            c = self._exact_triangles(centres.reshape(-1, 3)).reshape(na, ne)
            k = self._exact_triangles(corners.reshape(-1, 3)).reshape(na + 1, ne + 1)
            self._grid_tri = np.stack([c, k[:-1, :-1], k[1:, :-1], k[:-1, 1:], k[1:, 1:]], axis=-1)
            self._grid_step = step
        return self._grid_tri, self._grid_step

    def weights(self, directions: np.ndarray, method: str = "barycentric", out=None) -> tuple[np.ndarray, np.ndarray]:
        """For directions (m, 3): vertex indices (m, 3) and weights (m, 3) summing to 1. barycentric: the hull
        triangle the direction passes through, found through the grid table by a compiled loop (falling back to
        the whole hull); nearest: the closest measured direction with weight 1. ``out``: (indices int64, weights
        float64) arrays of shape (m, 3) to write into (the renderer's per-block call allocates nothing)."""
        from sonicverse_core.acoustics.kernels import all_finite, barycentric, nearest_direction

        d = np.ascontiguousarray(np.atleast_2d(directions), dtype=np.float64)
        if not all_finite(d):
            raise ConfigError("HRTF directions must be finite")
        idx, w = out if out is not None else (np.empty((len(d), 3), np.int64), np.empty((len(d), 3)))
        if method == "nearest":
            nearest_direction(d, self.directions, idx, w)
        else:
            grid, step = self._grid()
            barycentric(d, grid, step, self._inv, self._tri, idx, w)
        return idx, w

    def spectra(self, nfft: int) -> np.ndarray:
        """Spectra of the aligned filters at FFT size ``nfft``: (n, 2, nfft // 2 + 1) complex64 (cached)."""
        cache = self.__dict__.setdefault("_spectra", {})
        if nfft not in cache:
            cache[nfft] = np.fft.rfft(self.filters, nfft, axis=-1).astype(np.complex64)
        return cache[nfft]

    def lookup_spectra(self, directions: np.ndarray, nfft: int, method: str = "barycentric"):
        """Interpolated filter spectra (m, 2, nf) complex64 and onset delays (m, 2) s for unit vectors (m, 3).
        ``method``: barycentric (default) or nearest."""
        H = self.spectra(nfft)
        from sonicverse_core.acoustics.kernels import mix_spectra

        tri, w = self.weights(directions, method)
        out = np.empty((len(tri), 2, H.shape[-1]), np.complex64)
        mix_spectra(H, tri, w, np.ones((len(tri), H.shape[-1]), np.float32), np.zeros(len(tri)),
                    np.zeros((2, H.shape[-1]), np.complex64), out)
        return out, np.einsum("mk,mke->me", w, self.onsets[tri])

    def ambisonic_filters(self, order: int, nfft: int, length: int = 0) -> tuple[np.ndarray, float]:
        """Binaural decoding filters of real N3D spherical harmonics up to ``order``: (C, 2, nf) complex64 with
        C = (order + 1)^2, fitted by least squares over the measured directions (onset delays restored relative to
        the earliest one), truncated to ``length`` taps when given, and that common bulk delay in seconds. Cached
        per HRTF set (read-only): a renderer made per episode no longer pays the least-squares fit (~165 ms)."""
        cache = self.__dict__.setdefault("_ambisonic", {})
        key = (int(order), int(nfft), int(length))
        if key not in cache:
            H, bulk = self._ambisonic_filters(*key)
            H.setflags(write=False)
            cache[key] = (H, bulk)
        return cache[key]

    def _ambisonic_filters(self, order: int, nfft: int, length: int) -> tuple[np.ndarray, float]:
        from sonicverse_core.acoustics.ambisonics import real_sh

        bulk = float(self.onsets.min())
        rel = self.onsets - bulk
        f = np.fft.rfftfreq(nfft, 1 / self.sample_rate)
        H = self.spectra(nfft) * np.exp(-2j * np.pi * f[None, None, :] * rel[..., None])
        Y = real_sh(self.directions, order)  # (n, C)
        Hsh = np.linalg.lstsq(Y, H.reshape(len(H), -1), rcond=None)[0].reshape(Y.shape[1], 2, -1)
        if length:  # truncate the SH filters with a half-Hann fade over their last quarter
            h = np.fft.irfft(Hsh, nfft, axis=-1)[..., :length]
            fade = length // 4
            h[..., length - fade:] *= 0.5 * (1 + np.cos(np.pi * (np.arange(fade) + 1) / fade))
            Hsh = np.fft.rfft(h, nfft, axis=-1)
        return Hsh.astype(np.complex64), bulk
