"""Late reverb: an 8-line feedback delay network with per-line frequency-dependent decay (Jot & Chaigne 1991).

Each line's attenuation is a one-pole filter whose DC and Nyquist gains give the target RT60 at low (mean of
125-500 Hz) and high (mean of 4-8 kHz) frequencies: g = 10^(-3 M / (T fs)). Gains stay in (0, 1) and the pole in
(-1, 1) for any RT60 (clamped to 0.05..60 s), so the network is stable for every parameter a scene can produce;
the feedback matrix is orthogonal (Householder). Delays are at least one block long, so a block is processed with
array operations. The tail is normalised to unit energy and two decorrelated output mixes feed the two ears.
"""
from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

BASE_DELAYS = np.array([1031, 1327, 1523, 1723, 1949, 2179, 2437, 2719])  # samples at 48 kHz (primes)


class FDNReverb:
    def __init__(self, sample_rate: int, block: int, rt60_low: float = 0.5, rt60_high: float = 0.4):
        self.fs = sample_rate
        self.block = block
        n = len(BASE_DELAYS)
        self.delays = np.maximum(np.round(BASE_DELAYS * sample_rate / 48000).astype(int), block + 1)
        self.size = int(self.delays.max() + block + 1)
        self.buf = np.zeros((n, self.size))
        self.pos = 0
        self.A = np.eye(n) - 2.0 / n * np.ones((n, n))
        self.cl = np.where(np.arange(n) % 2 == 0, 1.0, -1.0) / np.sqrt(n)
        self.cr = np.where((np.arange(n) // 2) % 2 == 0, 1.0, -1.0) / np.sqrt(n)
        self.zi = np.zeros((n, 1))
        self.set_rt60(rt60_low, rt60_high)

    def set_rt60(self, rt_low: float, rt_high: float) -> None:
        rt_low = float(np.clip(rt_low, 0.05, 60.0))
        rt_high = float(np.clip(rt_high, 0.05, 60.0))
        self.rt60 = (rt_low, rt_high)
        g0 = 10 ** (-3.0 * self.delays / (rt_low * self.fs))
        gn = 10 ** (-3.0 * self.delays / (rt_high * self.fs))
        self.p = (g0 - gn) / (g0 + gn)  # in (-1, 1)
        self.b0 = g0 * (1 - self.p)
        m = float(np.mean(self.delays))
        self.norm = np.sqrt(13.8 * m / (rt_low * self.fs))

    def process(self, x: np.ndarray) -> np.ndarray:
        """x : (block,) mono send -> (2, block) float64 diffuse tail."""
        B = len(x)
        out = np.empty((2, B))
        done = 0
        while done < B:  # sub-blocks never longer than the shortest delay
            k = min(B - done, int(self.delays.min()) - 1)
            idx = (self.pos - self.delays[:, None] + np.arange(k)[None]) % self.size
            y = self.buf[np.arange(len(self.delays))[:, None], idx]
            f = np.empty_like(y)
            for i in range(len(y)):
                f[i], self.zi[i] = lfilter([self.b0[i]], [1.0, -self.p[i]], y[i], zi=self.zi[i])
            fb = self.A @ f + x[done:done + k][None] / np.sqrt(len(y))
            w = (self.pos + np.arange(k)) % self.size
            self.buf[:, w] = fb
            self.pos = (self.pos + k) % self.size
            out[0, done:done + k] = self.cl @ y
            out[1, done:done + k] = self.cr @ y
            done += k
        np.clip(self.buf, -1e6, 1e6, out=self.buf)
        self.buf[np.abs(self.buf) < 1e-25] = 0.0  # no denormals
        return out * self.norm
