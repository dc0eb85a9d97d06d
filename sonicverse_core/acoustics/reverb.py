"""Late reverb: an 8-line feedback delay network with per-line frequency-dependent decay (Jot & Chaigne 1991).

Each line's attenuation is a one-pole filter whose DC and Nyquist gains give the target RT60 at low (mean of
125-500 Hz) and high (mean of 4-8 kHz) frequencies: g = 10^(-3 M / (T fs)). Gains stay in (0, 1) and the pole in
(-1, 1) for any RT60 (clamped to 0.05..60 s), so the network is stable for every parameter a scene can produce;
the feedback matrix is orthogonal (Householder, O(n) per sample in a compiled loop). The tail is normalised to
unit energy and two decorrelated output mixes feed the two ears.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from sonicverse_core.scene.materials import BANDS

BASE_DELAYS = np.array([1031, 1327, 1523, 1723, 1949, 2179, 2437, 2719])  # samples at 48 kHz (primes)


class FDNReverb:
    def __init__(self, sample_rate: int, block: int, rt60_low: float = 0.5, rt60_high: float = 0.4):
        self.fs = sample_rate
        self.block = block
        n = len(BASE_DELAYS)
        self.delays = np.maximum(np.round(BASE_DELAYS * sample_rate / 48000).astype(np.int64), 8)
        self.size = int(self.delays.max() + 1)
        self.buf = np.zeros((n, self.size))
        self.pos = 0
        self.cl = np.where(np.arange(n) % 2 == 0, 1.0, -1.0) / np.sqrt(n)
        self.cr = np.where((np.arange(n) // 2) % 2 == 0, 1.0, -1.0) / np.sqrt(n)
        self.zi = np.zeros(n)
        self.set_rt60(rt60_low, rt60_high)

    def set_rt60(self, rt_low: float, rt_high: float, f_low: float = 500.0, f_high: float = 4000.0) -> None:
        """Decay times at two frequencies: each line's one-pole attenuation b0 / (1 - p z^-1) is fitted to give
        exactly RT60 rt_low at f_low and rt_high at f_high (solving |H|^2 at both for p), with |H| kept below the
        gain of a 60 s decay everywhere, so the network stays stable for any input."""
        rt_low = float(np.clip(rt_low, 0.05, 60.0))
        rt_high = float(np.clip(rt_high, 0.05, 60.0))
        self.rt60 = (rt_low, rt_high)
        g1 = 10 ** (-3.0 * self.delays / (rt_low * self.fs))
        g2 = 10 ** (-3.0 * self.delays / (rt_high * self.fs))
        c1 = np.cos(2 * np.pi * min(f_low, 0.45 * self.fs) / self.fs)
        c2 = np.cos(2 * np.pi * min(f_high, 0.49 * self.fs) / self.fs)
        r = (g1 / g2) ** 2  # |H(w1)|^2 / |H(w2)|^2 = (1 - 2 p c2 + p^2) / (1 - 2 p c1 + p^2)
        a, b = r - 1, 2 * (c2 - r * c1)
        with np.errstate(divide="ignore", invalid="ignore"):
            disc = np.sqrt(np.maximum(b * b - 4 * a * a, 0.0))
            roots = np.stack([(-b + disc) / (2 * a), (-b - disc) / (2 * a)])
        p = np.where(np.abs(a) < 1e-12, 0.0, np.where(np.abs(roots[0]) < 1, roots[0], roots[1]))
        p = np.clip(np.nan_to_num(p), -0.99, 0.99)
        b0 = g1 * np.sqrt(1 - 2 * p * c1 + p * p)
        gmax = 10 ** (-3.0 * self.delays / (60.0 * self.fs))
        peak = b0 / (1 - np.abs(p))  # the largest gain of the one-pole (at DC or Nyquist)
        self.b0 = np.where(peak > gmax, b0 * gmax / peak, b0)
        self.p = p
        m = float(np.mean(self.delays))
        # unit output energy for a unit impulse: each of the n lines carries ~ T fs / (13.8 m) of the injected energy
        # over its decay and the output mix sums the lines with weights 1/n
        self.norm = np.sqrt(13.8 * m * len(self.delays) / (rt_low * self.fs))

    def reset(self) -> None:
        """Silence the network (its state after a non-finite input: the renderer's recovery)."""
        self.buf[:] = 0.0
        self.zi[:] = 0.0
        self.pos = 0

    def process(self, x: np.ndarray) -> np.ndarray:
        """x : (block,) mono send -> (2, block) float64 diffuse tail (compiled per-sample loop)."""
        from sonicverse_core.acoustics.kernels import fdn_process

        out = np.empty((2, len(x)))
        self.pos = fdn_process(np.asarray(x, np.float64), out, self.buf, self.pos, self.delays, self.b0, self.p,
                               self.zi, self.cl, self.cr, self.norm)
        return out


def synth_tail(rt60: np.ndarray, sample_rate: int, seconds: float | None = None, seed: int = 0,
               gains: np.ndarray | None = None, coherence: np.ndarray | None = None) -> np.ndarray:
    """A two-channel late-reverb impulse response: octave-band noise per band of ``BANDS`` decaying at that band's
    RT60, normalised so that a flat RT60 and unit gains give unit energy per channel. (2, n) float64.

    gains (2, 9): each ear's amplitude per band (a binaural set's diffuse-field colouring; default 1);
    coherence (9,): the interaural coherence per band (default 0: two independent tails; 1: the same tail in both
    channels). Both channels carry the same energy whenever ``gains`` is the same for both."""
    from scipy.signal import butter, sosfilt

    from sonicverse_core.scene.materials import BANDS

    rt = np.clip(np.asarray(rt60, float), 0.05, 60.0)
    T = float(np.max(rt[2:])) if seconds is None else seconds
    n = int(min(T, 8.0) * sample_rate) + 1
    rng = np.random.default_rng(seed)
    noise = rng.normal(size=(2, n))
    g = np.ones((2, len(BANDS))) if gains is None else np.asarray(gains, float)
    rho = np.zeros(len(BANDS)) if coherence is None else np.clip(np.asarray(coherence, float), 0.0, 1.0)
    t = np.arange(n) / sample_rate
    out = np.zeros((2, n))
    edges = np.r_[BANDS / np.sqrt(2), BANDS[-1] * np.sqrt(2)]
    nyq = sample_rate / 2
    for b, f0 in enumerate(BANDS):
        lo, hi = edges[b] / nyq, min(edges[b + 1] / nyq, 0.999)
        if lo >= 0.999:
            continue
        if b == 0:
            sos = butter(4, hi, "lowpass", output="sos")
        elif b == len(BANDS) - 1 or hi >= 0.999:
            sos = butter(4, lo, "highpass", output="sos")
        else:
            sos = butter(4, [lo, hi], "bandpass", output="sos")
        x = sosfilt(sos, noise, axis=-1) * np.exp(-6.9078 * t / rt[b])
        a, c = np.sqrt((1 + rho[b]) / 2), np.sqrt((1 - rho[b]) / 2)  # mix to the band's coherence
        out[0] += g[0, b] * (a * x[0] + c * x[1])
        out[1] += g[1, b] * (a * x[0] - c * x[1])
    mid = float(np.mean(rt[4:7]))
    return out * np.sqrt(13.8155 / (mid * sample_rate))


def _tail_length(rt60, sample_rate: int) -> int:
    """Samples of :func:`synth_tail` for these RT60s (its default length)."""
    rt = np.clip(np.asarray(rt60, float), 0.05, 60.0)
    return int(min(float(np.max(rt[2:])), 8.0) * sample_rate) + 1


@lru_cache(maxsize=64)
def _partitions(rt60: tuple, sample_rate: int, B: int, P: int, seed: int, gains: tuple | None,
                coherence: tuple | None) -> np.ndarray:
    """A synthesised tail cut into P partitions of B samples, as spectra (2P, 2, B + 1) complex64, doubled so that
    the frequency-domain delay line never wraps; read-only (shared)."""
    g = None if gains is None else np.array(gains).reshape(2, -1)
    t = synth_tail(np.array(rt60), sample_rate, seed=seed, gains=g,
                   coherence=None if coherence is None else np.array(coherence))[:, : P * B]
    pad = np.zeros((2, P * B))
    pad[:, : t.shape[1]] = t
    parts = np.fft.rfft(pad.reshape(2, P, B).transpose(1, 0, 2), 2 * B, axis=-1)  # (P, 2, nf)
    H = np.concatenate([parts[::-1], parts[::-1]]).astype(np.complex64)
    H.setflags(write=False)
    return H


class ConvolutionReverb:
    """Uniformly partitioned overlap-save convolution (partitions of one block) with a synthesised tail per probe;
    the outputs of the probes around the listener are mixed with ramped weights. Exact per-band decay, no
    discrete echoes at the onset (noise, not a delay network), the binaural set's diffuse-field colouring and
    interaural coherence per band, the same energy in both channels; more cost than the FDN (the accuracy bench
    compares the two). The default late reverb."""

    def __init__(self, sample_rate: int, block: int, probe_rt60s, seconds: float = 3.0, seed: int = 0,
                 gains: np.ndarray | None = None, coherence: np.ndarray | None = None):
        self.B = B = block
        self.sample_rate = sample_rate
        self.nf = B + 1
        key = (lambda a: None if a is None else tuple(np.round(np.asarray(a, float).ravel(), 6)))
        n = [min(_tail_length(rt, sample_rate), int(seconds * sample_rate)) for rt in probe_rt60s]
        self.P = P = max(1, int(np.ceil(max(n) / B)))
        # tails are cached across renderers (an env builds one per episode): same parameters, same partitions
        self.H = [_partitions(key(rt), sample_rate, B, P, seed + k, key(gains), key(coherence))
                  for k, rt in enumerate(probe_rt60s)]
        self.fdl = np.zeros((P, self.nf), np.complex64)
        self._Y = np.zeros((2, self.nf), np.complex64)
        self.t = 0
        self.prev_in = np.zeros((1, B))
        self.w = None

    def reset(self) -> None:
        """Forget the input history (the renderer's recovery from a non-finite value)."""
        self.fdl[:] = 0
        self.prev_in[:] = 0.0

    def process(self, x: np.ndarray, weights: np.ndarray, shapes: np.ndarray | None = None) -> np.ndarray:
        """x (block,) mono send, or (G, block) sends each shaped by its row of ``shapes`` (G, 9) per-band amplitudes
        (the coupling of the room the group's sources are in); weights (n_probes,) summing to 1 -> (2, block)."""
        B, P = self.B, self.P
        x = np.atleast_2d(np.asarray(x, float))
        if self.prev_in.shape != x.shape:  # a first block with more groups: they start from silence
            prev = np.zeros(x.shape)
            prev[: len(self.prev_in)] = self.prev_in[: len(x)]
            self.prev_in = prev
        live = np.flatnonzero(np.any(x != 0, axis=1) | np.any(self.prev_in != 0, axis=1))
        frame = np.concatenate([self.prev_in[live], x[live]], axis=1)
        self.prev_in = x.copy()
        s = self.t % P
        X = np.fft.rfft(frame, axis=-1)  # only the groups that carry sound (one FFT each)
        if shapes is not None:
            shapes = np.asarray(shapes, float)[live]
        if len(live) == 0:
            self.fdl[s] = 0.0
        elif shapes is None or np.all(shapes == 1):
            self.fdl[s] = X.sum(0)
        else:  # a smooth per-band curve (linear in log frequency between band centres) per group
            if getattr(self, "_band_bins", None) is None:
                f = np.fft.rfftfreq(2 * B, 1 / self.sample_rate)
                lf = np.log2(np.maximum(f, BANDS[0]))
                self._band_bins = np.stack([np.interp(lf, np.log2(BANDS), e) for e in np.eye(len(BANDS))])
            self.fdl[s] = np.einsum("gf,gf->f", X, shapes @ self._band_bins)
        off = P - 1 - s
        w_old = weights if self.w is None else self.w
        ramp = (np.arange(B) + 1) / B
        out = np.zeros((2, B))
        from sonicverse_core.acoustics.kernels import fdl_mac

        Y = self._Y
        for k in np.flatnonzero((weights > 1e-4) | (w_old > 1e-4)):
            fdl_mac(self.fdl, self.H[k], off, Y)
            y = np.fft.irfft(Y, 2 * B, axis=-1)[:, B:]
            out += y * (w_old[k] + (weights[k] - w_old[k]) * ramp)
        self.w = np.asarray(weights, float).copy()
        self.t += 1
        return out
