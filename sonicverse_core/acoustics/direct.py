"""The direct sound (a subsystem of the renderer, :mod:`sonicverse_core.acoustics.state`): every source, or the
emitter its path puts it at, read from the history ring at a per-ear fractional delay (propagation + the HRTF's
onset delay, ramped across the block: Doppler without clicks) with a ramped gain (rolloff curve, bounded near-field
boost, directivity), filtered by overlap-save with the interpolated HRTF spectrum (barycentric over the measured
directions, onset-aligned) times a smooth per-band curve (air absorption x occlusion x spread), summed over sources
in the frequency domain; this block's and the previous block's filters are crossfaded at the output, so direction
changes never click. Without HRTFs: a constant-power panner (stereo with Woodworth's interaural delay, or mono)."""
from __future__ import annotations

import numpy as np

from sonicverse_core.acoustics.kernels import (accumulate, crossfade_into, direct_geometry, gather, mix_spectra,
                                               onset_delays, pan_spectra, shift_left, woodworth_delays)
from sonicverse_core.acoustics.fft import band_bins
from sonicverse_core.acoustics.probes import AIR_ABSORPTION, SPEED_OF_SOUND
from sonicverse_core.acoustics.state import PerSource
from sonicverse_core.scene.materials import BANDS

HEAD_RADIUS = 0.0875  # m: the stereo panner's head (Woodworth's ITD)


class DirectState(PerSource):
    """A listener's direct sound: per source its overlap-save input history (``hist`` (2, nfft)) and spectra
    (``X``), the previous block's per-ear delay, gain and filter (``delay``, ``gain``, ``spec``) and this block's
    (``delay_new``, ``gain_new``, ``spec_new``), the block's geometry (``dirs`` in the head frame, ``dist``,
    ``amp`` per band, ``delay0``), its band curve and HRTF weights; the inverse transform of both filters' sums
    (``acc`` -> ``both``) and the forward plans per source count (``ffts``)."""

    __slots__ = ("hist", "delay", "gain", "spec", "spec_new", "dirs", "dist", "gain_new", "amp", "delay0", "X",
                 "curve", "delay_new", "tri", "w", "acc", "both_fft", "both", "ffts")

    def __init__(self, cap: int, nfft: int):
        nf = nfft // 2 + 1
        rows = (("hist", (2, nfft), np.float32, 0), ("delay", (2,), np.float64, 0), ("gain", (), np.float64, 0),
                ("spec", (2, nf), np.complex64, 0), ("spec_new", (2, nf), np.complex64, 0),
                ("dirs", (3,), np.float64, 0), ("dist", (), np.float64, 0), ("gain_new", (), np.float64, 0),
                ("amp", (len(BANDS),), np.float32, 0), ("delay0", (), np.float64, 0),
                ("X", (2, nf), np.complex64, 0), ("curve", (nf,), np.float32, 0),
                ("delay_new", (2,), np.float64, 0), ("tri", (3,), np.int64, 0), ("w", (3,), np.float64, 0))
        super().__init__(cap, rows)
        from sonicverse_core.acoustics.fft import irfft_plan

        self.acc = np.zeros((2, 2, nf), np.complex64)
        self.both_fft, self.both = irfft_plan(self.acc, nfft)  # both filters' outputs, unnormalised

    def grow(self, cap: int) -> None:
        super().grow(cap)
        self.ffts = {}  # forward plans over hist[:n], per source count n (the buffers are new now)


class Direct:
    """The direct-sound subsystem of ``renderer`` (its sources' ring and arrays, its HRTF set or panner)."""

    name = "direct"

    def __init__(self, renderer):
        self.r = r = renderer
        cfg = r.cfg
        B, fs = cfg.block, cfg.sample_rate
        self.hrtf = r.hrtf
        self.taps = self.hrtf.taps if self.hrtf else 1
        margin = 0 if self.hrtf is None else max(16, self.taps // 4)  # room for the band curve's ringing
        self.nfft = 1 << int(np.ceil(np.log2(B + self.taps + margin)))
        self.nf = self.nfft // 2 + 1
        # smooth per-band curve over FFT bins: linear in log frequency between band centres
        self.band_matrix = band_bins(self.nfft, fs).astype(np.float32)
        self._onset_mean = self._diffuse = None

    # --- the subsystem protocol ----------------------------------------------------------------------------------
    def state(self, cap: int) -> DirectState:
        return DirectState(cap, self.nfft)

    def grow(self, st: DirectState | None, cap: int) -> None:
        if st is not None:
            st.grow(cap)

    def max_delay(self) -> float:
        return self.r.cfg.max_distance / SPEED_OF_SOUND + 0.01 + (self.hrtf.onsets.max() if self.hrtf else 0)

    def reset(self, st: DirectState) -> None:
        st.hist[:] = 0
        st.acc[:] = 0

    def render(self, st: DirectState, ls, lis, out) -> None:
        """Every source's direct sound (or, without line of sight, its path: ``ls.pos`` and ``ls.fwd`` are the
        emitters' positions and forwards, ``ls.occ`` their per-band amplitude), added into ``out``."""
        r, n = self.r, ls.n
        cfg, B = r.cfg, r.cfg.block
        dirs, dist, gain, amp, delay0 = st.dirs[:n], st.dist[:n], st.gain_new[:n], st.amp[:n], st.delay0[:n]
        direct_geometry(ls.pos, lis.position, ls.R, ls.fwd, r._dir_alpha[:n], r._dir_sharp[:n], ls.occ[:n],
                        AIR_ABSORPTION, *r._rolloff, SPEED_OF_SOUND, dirs, dist, gain, amp, delay0)
        curve = st.curve[:n]
        np.matmul(amp, self.band_matrix, out=curve)  # (n, nf) smooth per-band curves
        spec, delay = st.spec_new[:n], st.delay_new[:n]
        if self.hrtf is not None:
            tri, w = self.hrtf.weights(dirs, cfg.hrtf_interpolation, out=(st.tri[:n], st.w[:n]))
            spread = r._spread_frac[:n]
            mix_spectra(self.hrtf.spectra(self.nfft), tri, w, curve, spread, self.diffuse_spectrum(), spec)
            onset_delays(w, tri, self.hrtf.onsets, delay0, spread, self.mean_onset(), delay)
        else:
            pan_spectra(dirs, curve, cfg.output == "mono", spec)
            if cfg.output == "stereo":  # an interaural time and level panner
                woodworth_delays(dirs, delay0, HEAD_RADIUS / SPEED_OF_SOUND, delay)
            else:
                np.copyto(delay, delay0[:, None])
        fresh = ls.fresh[:n]
        p_delay, p_gain, p_spec = st.delay[:n], st.gain[:n], st.spec[:n]
        if ls.any_fresh:
            p_delay[fresh], p_gain[fresh], p_spec[fresh] = delay[fresh], gain[fresh], spec[fresh]
        h = st.hist[:n]
        shift_left(h.reshape(-1, self.nfft), B)
        gather(r._ring, r.write - B, p_delay, delay, float(cfg.sample_rate), p_gain[:, None], gain[:, None], h,
               self.nfft - B)  # (n, 2, B) fractional-delay taps, straight into the overlap-save input's end
        self._ffts(st, n).run()
        acc = st.acc
        changed = accumulate(st.X[:n], spec, p_spec, acc[1], acc[0])
        st.both_fft.run()  # (2 filters, 2 ears, nfft), unnormalised
        crossfade_into(st.both, r._ramp, 1.0 / self.nfft, changed, out)
        np.copyto(p_delay, delay)
        np.copyto(p_gain, gain)
        st.spec, st.spec_new = st.spec_new, st.spec  # this block's filters become the previous ones

    def _ffts(self, st: DirectState, n: int):
        """The forward plan over the first n sources' overlap-save histories (made once per source count)."""
        plan = st.ffts.get(n)
        if plan is None:
            from sonicverse_core.acoustics.fft import Plan

            plan = st.ffts[n] = Plan(st.hist[:n], st.X[:n])
        return plan

    def mean_onset(self) -> np.ndarray:
        """The HRTF set's mean onset per ear (2,): a fully spread source's."""
        if self._onset_mean is None:
            self._onset_mean = self.hrtf.onsets.mean(0)
        return self._onset_mean

    def diffuse_spectrum(self) -> np.ndarray:
        """Power-average HRTF magnitude over all measured directions (2, nf), zero phase: the fully spread source."""
        if self._diffuse is None:
            if self.hrtf is None:
                return np.zeros((2, self.nf), np.complex64)
            H = self.hrtf.spectra(self.nfft)
            self._diffuse = np.sqrt(np.mean(np.abs(H) ** 2, axis=0)).astype(np.complex64)
        return self._diffuse
