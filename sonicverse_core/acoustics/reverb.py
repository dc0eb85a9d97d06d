"""Late reverb: an 8-line feedback delay network with per-line frequency-dependent decay (Jot & Chaigne 1991).

Each line's attenuation is a one-pole filter whose DC and Nyquist gains give the target RT60 at low (mean of
125-500 Hz) and high (mean of 4-8 kHz) frequencies: g = 10^(-3 M / (T fs)). Gains stay in (0, 1) and the pole in
(-1, 1) for any RT60 (clamped to 0.05..60 s), so the network is stable for every parameter a scene can produce;
the feedback matrix is orthogonal (Householder, O(n) per sample in a compiled loop). The tail is normalised to
unit energy and two decorrelated output mixes feed the two ears.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from sonicverse_core.acoustics.fft import band_bins
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

    def process(self, x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """x : (block,) mono send -> (2, block) float64 diffuse tail (compiled per-sample loop); written into
        ``out`` when given (then nothing is allocated)."""
        from sonicverse_core.acoustics.late_kernels import fdn_process

        if out is None:
            out = np.empty((2, len(x)))
        if getattr(self, "_y", None) is None:
            self._y = np.empty(len(self.delays))
        self.pos = fdn_process(x, out, self.buf, self.pos, self.delays, self.b0, self.p, self.zi, self.cl, self.cr,
                               self.norm, self._y)
        return out


def decay_envelope(t: np.ndarray, rt: float, edt: float | None = None) -> np.ndarray:
    """Amplitude envelope of a band's tail: exp(-6.9 t / rt), or with ``edt`` (the baked early decay time, taken
    within [rt / 2, 1.5 rt]) two slopes whose Schroeder curve (the energy still to come, which the bake's EDT and
    RT60 are fitted to) falls its first 10 dB at the EDT's slope and the rest at the RT60's: the energy density
    starts as the one slope's would (the diffuse field's initial density does not depend on the absorption) and
    steps by EDT / RT60 where the slopes meet (EDT / 6 in; -1.5 dB for an EDT of 0.7 RT60). A room whose absorption
    sits on a few surfaces (an absorbing ceiling) decays faster at first than later, and its bake says by how
    much."""
    if edt is None or edt == rt:
        return np.exp(-6.9078 * t / rt)
    e = min(max(float(edt), 0.5 * rt), 1.5 * rt)
    t1 = e / 6.0
    return np.where(t < t1, np.exp(-6.9078 * t / e),
                    np.sqrt(e / rt) * np.exp(-6.9078 * (t1 / e + (t - t1) / rt)))


def synth_tail(rt60: np.ndarray, sample_rate: int, seconds: float | None = None, seed: int = 0,
               gains: np.ndarray | None = None, coherence: np.ndarray | None = None,
               edt: np.ndarray | None = None) -> np.ndarray:
    """A two-channel late-reverb impulse response: octave-band noise per band of ``BANDS`` decaying at that band's
    RT60 (with ``edt`` (9,), at first at the band's early decay time: :func:`decay_envelope`), normalised so that a
    flat RT60, no EDT and unit gains give unit energy per channel (an EDT shorter than the RT60 starts at the same
    level and holds less). (2, n) float64.

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
        x = sosfilt(sos, noise, axis=-1) * decay_envelope(t, rt[b], None if edt is None else edt[b])
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
                coherence: tuple | None, edt: tuple | None = None, m: int = 0):
    """A synthesised tail cut into P partitions of B samples, as spectra (2P, 2, B + 1) complex64, doubled so that
    the frequency-domain delay line never wraps; read-only (shared). With ``m`` (:func:`long_split`), the tail's
    first 2 m B samples in 2 m partitions of B and the rest in partitions of L = m B: (head, long spectra (2Q, 2,
    L + 1)); else (head, None)."""
    g = None if gains is None else np.array(gains).reshape(2, -1)
    t = synth_tail(np.array(rt60), sample_rate, seed=seed, gains=g,
                   coherence=None if coherence is None else np.array(coherence),
                   edt=None if edt is None else np.array(edt))[:, : P * B]
    return _cut(t, P, B, m)


def _cut(t: np.ndarray, P: int, B: int, m: int):
    """A tail (C, n <= P B) as (head, long) spectra: all of it in P partitions of B and None (``m`` 0), or its
    first 2 m B samples in 2 m partitions of B and the rest in partitions of m B."""
    if not m:
        return _spectra(t, P, B), None
    L = m * B
    Q = -(-(P * B - 2 * L) // L)
    return _spectra(t[:, : 2 * L], 2 * m, B), _spectra(t[:, 2 * L:], Q, L)


def _spectra(t: np.ndarray, P: int, B: int) -> np.ndarray:
    """A tail (C, n <= P B) cut into P partitions of B samples -> spectra (2P, C, B + 1) complex64, newest first and
    doubled (the frequency-domain delay line never wraps), read-only."""
    C = len(t)
    pad = np.zeros((C, P * B))
    pad[:, : t.shape[1]] = t
    parts = np.fft.rfft(pad.reshape(C, P, B).transpose(1, 0, 2), 2 * B, axis=-1)  # (P, C, nf)
    # C order whatever the FFT returns: NumPy 2's FFT keeps its input's memory order (channel outermost here) and
    # astype keeps that, so the tail reached fdl_mac as a strided array and its loop ran 2.8 times slower
    H = np.ascontiguousarray(np.concatenate([parts[::-1], parts[::-1]]), dtype=np.complex64)
    H.setflags(write=False)
    return H


DIRECT_SEED = 77_777  # the third, directional channel's noise: independent of every tail's two ears


@lru_cache(maxsize=64)
def _direct_partitions(rt60: tuple, sample_rate: int, B: int, P: int, seed: int, gains: tuple | None,
                       coherence: tuple | None, edt: tuple | None = None, m: int = 0):
    """A third channel for a tail of :func:`_partitions`' parameters: the same decay and colouring (the two ears'
    mean), noise independent of both ears; spectra (2P, 1, B + 1) complex64, read-only, cut as ``_partitions``
    cuts (head, long). What a tail's directional share is made of (:meth:`ConvolutionReverb.process`'s ``ears``):
    mixed into both ears with each ear's gain and delay, it is coherent between them, with the interaural delay of
    its direction."""
    g = None if gains is None else np.repeat(np.array(gains).reshape(2, -1).mean(0, keepdims=True), 2, axis=0)
    t = synth_tail(np.array(rt60), sample_rate, seed=seed + DIRECT_SEED, gains=g,
                   coherence=None if coherence is None else np.array(coherence),
                   edt=None if edt is None else np.array(edt))[:1, : P * B]
    return _cut(t, P, B, m)


LONG_MIN_PARTITIONS = 64  # a tail of fewer blocks is convolved in partitions of one block (RenderConfig's "auto")


def long_split(P: int) -> int:
    """How many blocks a long partition spans for a tail of ``P`` blocks (0: all partitions of one block). Each block
    multiplies 2 m partitions of B bins and a share 1 / m of the Q = P / m - 2 long partitions of m B bins: about
    (2 m + P / m) B bins, least at m = sqrt(P / 2) (a power of two, 4-64). A tail shorter than
    ``LONG_MIN_PARTITIONS`` blocks keeps one-block partitions: it is cheap already, and the environments' 0.1 s
    blocks (30 partitions of a 3 s tail) keep their sound to the bit."""
    if P < LONG_MIN_PARTITIONS:
        return 0
    m = 1 << int(round(math.log2(math.sqrt(P / 2))))
    m = min(max(m, 4), 64)
    return m if P > 3 * m else 0


class PortalEars:
    """The direction a tail arrives from, as :meth:`ConvolutionReverb.process` applies it: the diffuse share's
    amplitude (``diffuse``, sqrt(1 - beta), on both ears' own tails), the directional share's per-ear gains over
    the FFT's bins (``gains`` (2, block + 1): sqrt(beta) times that direction's level over the diffuse field's) and
    its per-ear delays in samples (``delays`` (2,): the interaural delay, on the far ear)."""

    __slots__ = ("diffuse", "gains", "delays", "band", "beta", "version")

    def __init__(self, block: int):
        self.diffuse = 1.0
        self.gains = np.zeros((2, block + 1), np.complex64)  # real values; the spectra's type (no cast per block)
        self.delays = np.zeros(2, np.int64)
        # what ``gains`` were made of (late_kernels.portal_curve): the direction's per-band ear gains (2, 9) and its
        # share; ``version`` counts the changes (long partitions make their own gains over their bins from these)
        self.band, self.beta, self.version = np.zeros((2, 9)), 0.0, 0

    def set(self, band: np.ndarray, beta: float, bins: np.ndarray, delays: np.ndarray) -> None:
        """A new direction: the per-band gains ``band`` (2, 9) of which ``beta`` arrives from it, over ``bins``
        (9, block + 1); ``delays`` (2,) per ear in samples. Allocates nothing."""
        from sonicverse_core.acoustics.late_kernels import portal_curve

        portal_curve(band, beta, bins, self.gains)
        self.band, self.beta = band, beta
        self.diffuse = math.sqrt(max(1.0 - beta, 0.0))
        self.delays[:] = delays
        self.version += 1


ITD_LINE_S = 0.001  # s: the directional share's delay line (Woodworth's largest ITD is 0.66 ms)


class ConvolutionReverb:
    """Partitioned overlap-save convolution with a synthesised tail per probe: partitions of one block, and where a
    tail spans ``LONG_MIN_PARTITIONS`` blocks or more (``partitions="auto"``) its part after the first 2 m blocks
    in partitions of m blocks, their work spread over the blocks (:mod:`~sonicverse_core.acoustics.long_tail`; the
    same convolution, cheaper: ``bench accuracy``'s reverb knob times both); the outputs of the probes around the
    listener are mixed with ramped weights. Exact per-band decay, no discrete echoes at the onset (noise, not a
    delay network), the binaural set's diffuse-field colouring and interaural coherence per band, the same energy
    in both channels; more cost than the FDN (the accuracy bench compares the two). The default late reverb."""

    def __init__(self, sample_rate: int, block: int, probe_rt60s, seconds: float = 3.0, seed: int = 0,
                 gains: np.ndarray | None = None, coherence: np.ndarray | None = None, groups: int = 1,
                 probe_edts=None, direct: bool = False, direct_seed: int | None = None, partitions: str = "auto",
                 stagger: float = 0.0):
        from sonicverse_core.acoustics.fft import irfft_plan, rfft_plan

        self.B = B = block
        self.sample_rate = sample_rate
        self.nf = B + 1
        key = (lambda a: None if a is None else tuple(np.round(np.asarray(a, float).ravel(), 6)))
        n = [min(_tail_length(rt, sample_rate), int(seconds * sample_rate)) for rt in probe_rt60s]
        n_blocks = max(1, int(np.ceil(max(n) / B)))
        if partitions not in ("auto", "uniform"):
            raise ValueError(f"partitions must be auto or uniform, got {partitions!r}")
        # "auto": a long tail's part after its first 2 m blocks in partitions of m blocks (long_tail.py);
        # "uniform": every partition one block long
        self.m = m = long_split(n_blocks) if partitions == "auto" else 0
        self.P = P = 2 * m if m else n_blocks  # the partitions of one block
        # tails are cached across renderers (an env builds one per episode): same parameters, same partitions
        edts = [None] * len(probe_rt60s) if probe_edts is None else probe_edts
        parts = [_partitions(key(rt), sample_rate, B, n_blocks, seed + k, key(gains),
                             key(coherence), key(e), m)
                 for k, (rt, e) in enumerate(zip(probe_rt60s, edts))]
        self.H = [h for h, _ in parts]
        # ``direct``: a third channel per tail, for a share that arrives from one direction (``process``'s ears);
        # ``direct_seed`` (default ``seed``): reverbs that never play the same tail at once may share these
        ds = seed if direct_seed is None else direct_seed
        dparts = [_direct_partitions(key(rt), sample_rate, B, n_blocks, ds + k, key(gains),
                                     key(coherence), key(e), m)
                  for k, (rt, e) in enumerate(zip(probe_rt60s, edts))] if direct else None
        self.Hd = None if dparts is None else [h for h, _ in dparts]
        self.long = None
        if m:
            from sonicverse_core.acoustics.long_tail import LongPartitions

            self.long = LongPartitions(sample_rate, B, m, groups, [h for _, h in parts],
                                       None if dparts is None else [h for _, h in dparts], stagger=stagger)
        self.fdl = np.zeros((P, self.nf), np.complex64)
        self.t = 0
        self.G = groups
        # per block, in fixed buffers: [previous | this] block of every group's send -> spectra; one tail's
        # spectrum -> its samples (the inverse is unnormalised: 1 / 2B goes into the output gain)
        self._frame = np.zeros((groups, 2 * B), np.float32)
        self._fwd, self._X = rfft_plan(self._frame)
        self._Y = np.zeros((2, self.nf), np.complex64)
        self._inv, self._y = irfft_plan(self._Y, 2 * B)
        if direct:  # the directional channel's spectrum, its two ears', their samples, and the ears' delay line
            self._M = np.zeros((1, self.nf), np.complex64)
            self._Yd = np.zeros((2, self.nf), np.complex64)
            self._inv_d, self._yd = irfft_plan(self._Yd, 2 * B)
            self._dacc = np.zeros((2, B))
            self.D = int(np.ceil(ITD_LINE_S * sample_rate))
            self._dhist = np.zeros((2, self.D + B))
            self._dlast = np.zeros(2, np.int64)
        self._live = np.zeros(groups, bool)
        self._curves = np.ones((groups, self.nf), np.float32)
        self._shaped, self._shapes_key, self._last_shapes = False, None, None
        self.w = np.zeros(len(self.H))
        self._w_set = False
        # compile (or load) the per-block kernels now: one first called in the first block with sound would stall a
        # real-time caller for as long as numba takes to compile it (the stream's watchdog calls that a lost device)
        from sonicverse_core.acoustics.late_kernels import delayed_add, fdl_fill, live_rows

        live_rows(self._frame[:, B:], self._frame[:, :B], self._live)
        fdl_fill(self._X, self._curves, self._live, False, self.fdl[0])
        if direct:
            delayed_add(self._dhist, self._dlast, self._dlast, np.zeros((2, B)))

    def reset(self) -> None:
        """Forget the input history (the renderer's recovery from a non-finite value)."""
        self.fdl[:] = 0
        self._frame[:] = 0.0
        if self.Hd is not None:
            self._dhist[:] = 0.0
        if self.long is not None:
            self.long.reset()

    def _set_shapes(self, shapes) -> None:
        """Per-group per-band amplitudes (G, 9) -> smooth curves over the FFT bins (linear in log frequency between
        band centres); none at all (a plain sum) when every amplitude is 1. Amplitudes equal to the last ones
        change nothing (a listener who steps within a room re-keys the shapes without changing them)."""
        shapes = np.asarray(shapes, float).reshape(self.G, len(BANDS))
        if self._last_shapes is not None and np.array_equal(shapes, self._last_shapes):
            return
        self._last_shapes = shapes.copy()
        self._shaped = not np.all(shapes == 1)
        if self._shaped:
            self._curves[:] = shapes @ band_bins(2 * self.B, self.sample_rate)
            if self.long is not None:
                np.matmul(shapes, self.long.bins, out=self.long.curves, casting="unsafe")

    def process(self, x: np.ndarray, weights: np.ndarray, shapes: np.ndarray | None = None,
                out: np.ndarray | None = None, level: tuple = (1.0, 1.0), shapes_key=None,
                ears: np.ndarray | None = None) -> np.ndarray:
        """x (block,) mono send, or (G, block) sends each shaped by its row of ``shapes`` (G, 9) per-band amplitudes
        (the coupling of the room the group's sources are in); weights (n_probes,) summing to 1 -> (2, block)
        float64, added into ``out`` when given, scaled by the late level ramped from level[0] to level[1].
        ``shapes_key``: a value that changes whenever ``shapes`` does (the curves are rebuilt then; without a key,
        every block). ``ears``: where part of the tail arrives from one direction (a :class:`PortalEars`; a
        reverb made with ``direct`` only): the ears' own tails at its ``diffuse`` amplitude, plus the third channel
        with each ear's gains over the bins and each ear's delay (ramped from the last block's over this one: the
        head turns without a click). The share is coherent between the ears and lags in the far one, as sound
        through a doorway does. With ``out`` and a key, a block allocates nothing."""
        from sonicverse_core.acoustics.kernels import shift_left
        from sonicverse_core.acoustics.late_kernels import delayed_add, fdl_fill, fdl_mac, live_rows, mix_ramped

        B, P = self.B, self.P
        x = x.reshape(-1, B)
        if not isinstance(weights, np.ndarray):
            weights = np.asarray(weights, float)
        if len(x) != self.G:
            raise ValueError(f"expected {self.G} send(s), got {len(x)}")
        if out is None:
            out = np.zeros((2, B))
        if shapes_key is None or shapes_key != self._shapes_key:
            if shapes is None:
                self._shaped, self._last_shapes = False, None
            else:
                self._set_shapes(shapes)
            self._shapes_key = shapes_key
        frame = self._frame
        shift_left(frame, B)  # this block's first half: the previous block
        frame[:, B:] = x
        s = self.t % P
        if live_rows(frame[:, B:], frame[:, :B], self._live):
            self._fwd.run()  # every group's spectrum (a few rows of 2B: cheaper than picking the live ones)
            fdl_fill(self._X, self._curves, self._live, self._shaped, self.fdl[s])
        else:
            self.fdl[s].fill(0)
        off = P - 1 - s
        if not self._w_set:  # the first block: no ramp from an earlier mix
            self.w[:] = weights
            self._w_set = True
        scale = 1.0 / (2 * B)
        diffuse = 1.0
        if ears is not None:
            if self.Hd is None:
                raise ValueError("a direction needs a reverb made with direct=True")
            self._dacc.fill(0.0)
            diffuse = ears.diffuse
        for k in range(len(self.H)):
            w0, w1 = float(self.w[k]), float(weights[k])
            if w0 <= 1e-4 and w1 <= 1e-4:
                continue
            fdl_mac(self.fdl, self.H[k], off, self._Y)
            if ears is not None:
                fdl_mac(self.fdl, self.Hd[k], off, self._M)
                np.multiply(self._M, ears.gains, out=self._Yd)
                self._inv_d.run()
                mix_ramped(self._yd, w0, w1, level[0], level[1], scale, self._dacc)
            self._inv.run()
            mix_ramped(self._y, w0, w1, level[0], level[1], scale * diffuse, out)
        if self.long is not None:  # the tail after its first 2 L samples
            self.long.process(frame[:, B:], self._live, self.w, weights, level[0], level[1], diffuse, ears,
                              self._shaped, out, self._dacc if self.Hd is not None else None)
        if self.Hd is not None:  # the directional share through its delay line (silence in it when no direction)
            if ears is None:
                self._dacc.fill(0.0)
            shift_left(self._dhist, B)
            self._dhist[:, self.D:] = self._dacc
            d1 = self._dlast if ears is None else ears.delays
            delayed_add(self._dhist, self._dlast, d1, out)
            self._dlast[:] = d1
        self.w[:] = weights
        self.t += 1
        return out
