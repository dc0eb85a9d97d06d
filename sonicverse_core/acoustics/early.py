"""Early reflections: image sources of a probe's proxy box (Allen & Berkley 1979).

For a box [lo, hi] and a source inside it, the image positions along each axis are x' = (1 - 2q) x + 2 m L
(box-local coordinates, q in {0, 1}, m integer); such an image has reflected |m - q| times off the low wall and
|m| times off the high wall of that axis. All images up to a reflection ``order`` are enumerated once per order
(the lattice); ``kernels.image_taps`` places them for every source each block. A wall reflects sqrt(1 - alpha) of the
amplitude, alpha its material's mean absorption over 500 Hz - 2 kHz; an open side (no surface within reach of the
probe) reflects nothing.
"""
from __future__ import annotations

import itertools
from functools import lru_cache

import numpy as np

from sonicverse_core.acoustics.state import PerSource
from sonicverse_core.scene.materials import BANDS, get_material

MID_BANDS = (BANDS >= 500) & (BANDS <= 2000)


@lru_cache(maxsize=8)
def lattice(order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """q (K, 3), m (K, 3) and the reflection counts (K, 6) (-x, +x, -y, +y, -z, +z) of every image with
    1 <= total reflections <= order."""
    qs, ms, counts = [], [], []
    rng = range(-order, order + 1)
    for q in itertools.product((0, 1), repeat=3):
        for m in itertools.product(rng, repeat=3):
            c = []
            for a in range(3):
                c += [abs(m[a] - q[a]), abs(m[a])]
            if 1 <= sum(c) <= order:
                qs.append(q)
                ms.append(m)
                counts.append(c)
    return np.array(qs, float), np.array(ms, float), np.array(counts, float)


def wall_reflectance(materials) -> np.ndarray:
    """Amplitude reflection factor (6,) of the proxy box's walls (-x, +x, -y, +y, -z, +z)."""
    r = []
    for name in materials:
        if name == "Transparent":
            r.append(0.0)
        else:
            a = float(np.mean(np.asarray(get_material(name).absorption)[MID_BANDS]))
            r.append(np.sqrt(max(0.0, 1.0 - a)))
    return np.array(r)


def image_amplitudes(reflect: np.ndarray, order: int) -> np.ndarray:
    """Amplitude factor (K,) of every image of the lattice: the product of its walls' reflection factors
    (the image positions themselves are placed per block by ``kernels.image_taps``)."""
    c = lattice(order)[2]
    return np.prod(np.where(c > 0, reflect[None, :] ** c, 1.0), axis=1)


class EarlyState(PerSource):
    """A listener's early reflections: per source and image the previous block's delay, gain and second-order
    spherical-harmonic weights (``delay``, ``gain``, ``Y``) and this block's (``*_new``); the block's ambisonic
    signals (``amb``), the binaural decoder's overlap-save history and transforms (``hist``, ``fft``, ``A``,
    ``acc``, ``ifft``) and its output ``y``; the probe whose box is imaged (``probe``, found at ``probe_key``)."""

    __slots__ = ("delay", "gain", "Y", "delay_new", "gain_new", "Y_new", "amb", "tmp", "hist", "fft", "A", "acc",
                 "ifft", "y", "probe_key", "probe")

    def __init__(self, cap: int, K: int, C: int, block: int, nfft: int):
        rows = (("delay", (K,), np.float64, 0), ("gain", (K,), np.float64, 0), ("Y", (K, C), np.float64, 0),
                ("delay_new", (K,), np.float64, 0), ("gain_new", (K,), np.float64, 0),
                ("Y_new", (K, C), np.float64, 0))
        super().__init__(cap, rows)
        self.amb = np.zeros((C, block), np.float32)
        self.tmp = np.zeros(block, np.float32)
        self.hist = self.fft = self.A = self.acc = self.ifft = None
        self.probe_key, self.probe = None, -1
        if nfft:  # decoded binaurally
            from sonicverse_core.acoustics.fft import irfft_plan, rfft_plan

            self.hist = np.zeros((C, nfft), np.float32)
            self.fft, self.A = rfft_plan(self.hist)
            self.acc = np.zeros((2, nfft // 2 + 1), np.complex64)
            self.ifft, self.y = irfft_plan(self.acc, nfft)
        else:
            self.y = np.zeros((2, block), np.float32)


class EarlyReflections:
    """The early-reflection subsystem of ``renderer`` (:mod:`sonicverse_core.acoustics.state`): image sources (order
    1 or 2) of the proxy box of the probe nearest the listener in its room, from the actual source and listener
    positions, each a ramped fractional-delay tap encoded in second-order ambisonics in the head frame and decoded
    binaurally by least-squares spherical-harmonic HRTF filters (or to stereo / mono)."""

    name = "early"
    ORDER = 2  # the ambisonic order

    def __init__(self, renderer):
        self.r = r = renderer
        cfg, scene, probes = r.cfg, r.scene, r.probes
        B, fs = cfg.block, cfg.sample_rate
        self.K = len(lattice(cfg.er_order)[0])
        self.C = (self.ORDER + 1) ** 2
        self.refl = [wall_reflectance(p.box_materials) for p in probes]
        self.probe_rooms = [scene.room_at(p.position[:2]) if scene is not None and scene.rooms else None
                            for p in probes]
        # the image sources' box: the probe's proxy box within its room's footprint (rays from a probe that
        # faces a doorway run on into the next room; the room's walls are where the reflections are)
        self.box = []
        for p, room in zip(probes, self.probe_rooms):
            lo, hi = p.box_lo.copy(), p.box_hi.copy()
            if room is not None:
                lo[:2] = np.maximum(lo[:2], room.footprint.min(0))
                hi[:2] = np.minimum(hi[:2], room.footprint.max(0))
                if np.any(hi <= lo) or np.any(p.position < lo) or np.any(p.position > hi):
                    lo, hi = p.box_lo, p.box_hi
            self.box.append((lo, hi))
        self.amp = {}
        self.hrtf = r.hrtf
        if self.hrtf is not None:
            taps = self.hrtf.taps
            # 2nd-order SH smooths the HRTF above ~2 kHz anyway: 3 ms of filter (interaural delay included)
            er_len = int(0.003 * fs)
            max_rel = int(np.ceil((self.hrtf.onsets.max() - self.hrtf.onsets.min()) * fs))
            self.nfft = 1 << int(np.ceil(np.log2(B + er_len + 16)))
            big = 1 << int(np.ceil(np.log2(taps + max_rel + 64)))
            self.filters, self.bulk = self.hrtf.ambisonic_filters(self.ORDER, max(big, self.nfft), er_len)
            if big > self.nfft:
                h = np.fft.irfft(self.filters, big, axis=-1)[..., :er_len]
                self.filters = np.fft.rfft(h, self.nfft, axis=-1).astype(np.complex64)
        else:
            self.nfft, self.bulk = 0, 0.0
            dec = np.zeros((2, self.C))
            dec[:, 0] = 0.5 if cfg.output == "stereo" else np.sqrt(0.5)
            if cfg.output == "stereo":
                dec[:, 1] = [0.5 / np.sqrt(3), -0.5 / np.sqrt(3)]
            self.decode = dec.astype(np.float32)

    # --- the subsystem protocol ----------------------------------------------------------------------------------
    def state(self, cap: int) -> EarlyState:
        return EarlyState(cap, self.K, self.C, self.r.cfg.block, self.nfft)

    def grow(self, st: EarlyState | None, cap: int) -> None:
        if st is not None:
            st.grow(cap)

    def max_delay(self) -> float:
        from sonicverse_core.acoustics.probes import SPEED_OF_SOUND

        r = self.r
        return r.direct.max_delay() + 3 * r.cfg.er_order * float(
            np.max([np.max(p.box_hi - p.box_lo) for p in r.probes])) / SPEED_OF_SOUND

    def reset(self, st: EarlyState) -> None:
        st.amb[:] = 0
        if st.hist is not None:
            st.hist[:] = 0
            st.acc[:] = 0

    def nearest_probe(self, st: EarlyState, p: np.ndarray) -> int:
        """The probe for the listener's early reflections: the nearest one in the listener's room (the nearest
        overall where the room is unknown or has none); cached per listener while it stays within 5 cm."""
        from sonicverse_core.acoustics.kernels import farther

        r = self.r
        if st.probe_key is None or farther(st.probe_key, p, 0.05):
            d2 = np.sum((r._probe_pos - p) ** 2, axis=1)
            if r.coupling is not None:  # the slice's room labels: a lookup, not polygon tests
                room = r.coupling.room_of(p[None, :2])[0]
                room = r.coupling.rooms[room] if room >= 0 else None
            else:
                room = r.scene.room_at(p[:2]) if r.scene is not None and r.scene.rooms else None
            same = np.array([q is not None and q is room for q in self.probe_rooms]) if room is not None else None
            if same is not None and same.any():
                d2 = np.where(same, d2, np.inf)
            st.probe_key, st.probe = p.copy(), int(np.argmin(d2))
        return st.probe

    def render(self, st: EarlyState, ls, lis, out) -> None:
        """Image sources of the nearest probe's box, added into ``out``. ``ls.pos``: the emitters (a source heard
        along a path is imaged from where its path puts it: outside the listener's room, it has no images, and its
        room's sound arrives by the coupled late reverb)."""
        from sonicverse_core.acoustics.kernels import accumulate_sh, add_tail, encode_taps, image_taps, shift_left
        from sonicverse_core.acoustics.probes import SPEED_OF_SOUND

        r, n = self.r, ls.n
        cfg, B = r.cfg, r.cfg.block
        k = self.nearest_probe(st, lis.position)
        if k not in self.amp:
            self.amp[k] = image_amplitudes(self.refl[k], cfg.er_order)
        q, m, _ = lattice(cfg.er_order)
        delay, gain, Y = st.delay_new[:n], st.gain_new[:n], st.Y_new[:n]
        lo, hi = self.box[k]
        image_taps(ls.pos, lo, hi, q, m, self.amp[k], lis.position, ls.R, *r._rolloff, ls.occ[:n], self.bulk,
                   SPEED_OF_SOUND, delay, gain, Y)
        fresh = ls.fresh[:n]
        pd, pg, pY = st.delay[:n], st.gain[:n], st.Y[:n]
        if ls.any_fresh:
            pd[fresh], pg[fresh], pY[fresh] = delay[fresh], gain[fresh], Y[fresh]
        amb = st.amb
        encode_taps(r._ring, r.write - B, pd, delay, float(cfg.sample_rate), pg, gain, pY, Y, r._ramp, amb, st.tmp)
        st.delay, st.delay_new = st.delay_new, st.delay
        st.gain, st.gain_new = st.gain_new, st.gain
        st.Y, st.Y_new = st.Y_new, st.Y
        if self.hrtf is None:
            np.matmul(self.decode, amb, out=st.y)
            add_tail(st.y, 1.0, out)
            return
        h = st.hist
        shift_left(h, B)
        h[:, -B:] = amb
        st.fft.run()
        accumulate_sh(st.A, self.filters, st.acc)
        st.ifft.run()
        add_tail(st.y, 1.0 / self.nfft, out)
