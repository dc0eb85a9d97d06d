"""The block renderer: N sources, one or more listeners, (2, block) float32 binaural output per listener.

Signal flow per block (all sources at once, array operations only; state is preallocated when sources and
listeners are added):

* Sources write their next dry block (sound-bank/file signals, looping or one-shot, or live pushed blocks) into a
  history ring.
* Direct path, per listener: every source is read from the ring at a per-ear fractional delay (propagation +
  the HRTF's onset delay, ramped across the block: Doppler without clicks) with a ramped gain (rolloff curve,
  bounded near-field boost, directivity). The delayed signals are filtered by overlap-save: one FFT per source and
  ear, multiplied by the interpolated HRTF spectrum (barycentric over the measured directions, onset-aligned) times
  a smooth per-band curve (air absorption x occlusion x spread), and summed over sources in the frequency domain.
  The sum is taken with this block's and the previous block's filters and crossfaded at the output, so direction
  changes never click.
* Occlusion: Embree rays from each source to the listener through static and dynamic geometry; the transmission
  of every part crossed (once per part) multiplies per band. Rays are cast only for segments that moved or when
  the scene's dynamic state changed (a door), and only where some part's bounding box meets the segment; the
  result is smoothed across blocks.
* Propagation paths (``paths.py``): a source without line of sight on the scene's ear-height slice reaches the
  listener along the shortest open path round corners and through doorways (per-band diffraction at every bend,
  door apertures); path and wall transmission add in energy and play from one emitter per source placed at their
  energy-weighted blend of direction and length.
* Early reflections: image sources (order 1 or 2) of the proxy box of the probe nearest the listener, from the
  actual source and listener positions, each a ramped fractional-delay tap encoded in second-order ambisonics in
  the head frame and decoded binaurally by least-squares spherical-harmonic HRTF filters.
* Late reverb: per listener, partitioned convolution with a tail synthesised per probe (octave-band noise decaying
  at the probe's RT60 in each band, coloured by the HRTF set's diffuse field and given its interaural coherence per
  band; no discrete echoes at the onset), or a cheaper FDN; the probes of the listener's room are mixed by
  inverse-distance weights. Sources in other rooms send through the rooms' coupling (``coupling.py``: a per-band
  energy balance through doors and walls), one send per room, filtered per band. Each source's send is delayed
  by its travel time plus the mixing time (sqrt(V) ms, Polack), so the tail starts after the direct sound and the
  early reflections, and falls with distance (Barron). With probes baked per room (``BakeConfig.per_room``) and
  convolution, each send feeds two tails instead, on independent noise: the listener's room's own decay (its tails
  with doors open and shut, blended as its doors are) and the coupled rooms' slowest mode, with the energies of the
  rooms' energy balance in time (:meth:`RoomCoupling.late_split`): a dead room beside a live one decays with two
  slopes. A slowest mode ringing in another room is heard from its doorway, in part (the level differences of
  that direction; ``late.LateReverb._portal``).
* A transparent limiter acts only when a block would exceed 0.99; the output is finite and within [-1, 1].

Nothing a caller feeds in can silence the renderer for good: signals are checked where they enter (a file or bank
signal with a NaN is refused; a live block's non-finite samples become zeros and are counted in
``stats["nonfinite_input"]``), gains are bounded, and should a listener's block still come out non-finite (its
recursive states poisoned), that listener's filter, reflection and reverb states are cleared within the block and
``stats["recoveries"]`` counts it.

In steady state (sources and listeners each within the occlusion tolerance of where their rays were last cast, no
door moving; heads may turn and gains change) a block written into preallocated outputs (``render_block(outs)``)
allocates nothing: FFTs run on fixed buffers (``fft.py``), every per-block expression is a compiled kernel writing
into per-listener buffers, and no kernel allocates (tests/test_poison.py counts NumPy's and numba's allocations).
Recasting rays, finding new paths, adding sources and the first block of a listener allocate.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from sonicverse_core.acoustics.config import RenderConfig  # noqa: F401 - re-exported: the renderer's settings
from sonicverse_core.acoustics.early import image_amplitudes, lattice, wall_reflectance
from sonicverse_core.acoustics.kernels import (accumulate, accumulate_sh, add_tail, all_finite, crossfade_into,
                                               direct_geometry, distance_gains, encode_taps, farther, gather,
                                               head_rotation, image_taps, limit, mix_spectra, onset_delays,
                                               pan_spectra, read_sources, scale_into, woodworth_delays, shift_left,
                                               smooth_toward)
from sonicverse_core.acoustics.late import MAX_MIXING_TIME, SLOW_SEED, LateReverb
from sonicverse_core.acoustics.occlusion import Occlusion, may_occlude

from sonicverse_core.acoustics.probes import AIR_ABSORPTION, SPEED_OF_SOUND
from sonicverse_core.acoustics.sources import Listener, Source, grown as _grown
from sonicverse_core.errors import ConfigError, PoseError
from sonicverse_core.scene.materials import BANDS

HEAD_RADIUS = 0.0875  # m: the stereo panner's head (Woodworth's ITD)


@lru_cache(maxsize=8)
def _hrtf(name: str, sample_rate: int, taps: int):
    """The HRTF interpolator for a set ('kemar' or a SOFA path) at a rate, shared by renderers (read-only)."""
    from assets_manifest.hrtf import kemar, load_sofa
    from sonicverse_core.acoustics.hrtf import HrtfInterpolator

    return HrtfInterpolator(kemar() if name == "kemar" else load_sofa(name), sample_rate, taps=taps)


def rolloff_params(cfg: RenderConfig) -> tuple:
    """(mode, d0, max distance, near-field factor) of the distance-law kernels."""
    return (("log", "linear", "none").index(cfg.rolloff),
            max(cfg.min_distance, 1.0) if cfg.rolloff == "log" else cfg.min_distance, cfg.max_distance,
            cfg.near_field_gain / 9)


def distance_gain(d, cfg: RenderConfig) -> np.ndarray:
    """Rolloff gain (Resonance Audio's curves) times the near-field boost under 1 m (bounded: at most
    1 + near_field_gain at 0.1 m and closer); the same kernel the renderer uses per block."""
    d = np.asarray(d, float)
    out = np.empty(d.size)
    distance_gains(d.ravel(), *rolloff_params(cfg), out)
    return out.reshape(d.shape)


class AcousticRenderer(LateReverb):
    def __init__(self, scene=None, config: RenderConfig = RenderConfig(), probes=None, hrtf=None):
        self.cfg = cfg = config
        self.scene = scene
        self.sources: list[Source] = []
        self.listeners: list[Listener] = []
        self.subsystems = ["direct", "distance", "air_absorption"]
        B, fs = cfg.block, cfg.sample_rate
        self.hrtf = None
        if cfg.output == "binaural":
            taps = cfg.hrtf_taps or max(32, int(round(0.004 * fs)))
            self.hrtf = hrtf or _hrtf(cfg.hrtf, fs, taps)
            self.subsystems.append("hrtf")
        self.taps = self.hrtf.taps if self.hrtf else 1
        margin = 0 if self.hrtf is None else max(16, self.taps // 4)  # room for the band curve's ringing
        self.nfft = 1 << int(np.ceil(np.log2(B + self.taps + margin)))
        self.nf = self.nfft // 2 + 1
        freqs = np.fft.rfftfreq(self.nfft, 1 / fs)
        # smooth per-band curve over FFT bins: linear in log frequency between band centres
        lf = np.log2(np.maximum(freqs, BANDS[0]))
        eye = np.eye(len(BANDS))
        self._band_matrix = np.stack([np.interp(lf, np.log2(BANDS), e) for e in eye]).astype(np.float32)
        self.occlusion = None
        if cfg.occlusion and scene is not None and may_occlude(scene):
            self.occlusion = Occlusion(scene, cfg.occlusion_tolerance, cfg.occlusion_rays_per_block)
            self.subsystems.append("occlusion")
        self.stats = self.occlusion.stats if self.occlusion else {"occlusion_rays": 0, "occlusion_skipped": 0}
        self.paths, graph = None, None
        if self.occlusion is not None and (cfg.paths or cfg.late_reverb and scene.rooms):
            from sonicverse_core.acoustics.paths import path_graph

            graph = path_graph(scene, cfg.path_cell, caster=self.occlusion.caster)
        if cfg.paths and graph is not None:
            from sonicverse_core.acoustics.paths import PathState

            if len(graph.nodes):  # a scene with no corner to go round needs none
                self.paths = PathState(graph, cfg.diffraction, cfg.occlusion_tolerance,
                                       cfg.occlusion_rays_per_block)
                self.subsystems.append("paths")
        self.stats.update(paths=0, room_reverbs=0, rooms_sending=0)
        self.stats.update(nonfinite_input=0, recoveries=0)
        enclosed = [p for p in (probes or []) if p.enclosed > 0.5]
        self.probes = enclosed or None
        if self.probes:
            self._probe_pos = np.array([p.position for p in self.probes])
        self._er = cfg.early_reflections and self.probes is not None
        if self._er:
            self._K = len(lattice(cfg.er_order)[0])
            self._refl = [wall_reflectance(p.box_materials) for p in self.probes]
            self._probe_rooms = [scene.room_at(p.position[:2]) if scene is not None and scene.rooms else None
                                 for p in self.probes]
            # the image sources' box: the probe's proxy box within its room's footprint (rays from a probe that
            # faces a doorway run on into the next room; the room's walls are where the reflections are)
            self._er_box = []
            for p, room in zip(self.probes, self._probe_rooms):
                lo, hi = p.box_lo.copy(), p.box_hi.copy()
                if room is not None:
                    lo[:2] = np.maximum(lo[:2], room.footprint.min(0))
                    hi[:2] = np.minimum(hi[:2], room.footprint.max(0))
                    if np.any(hi <= lo) or np.any(p.position < lo) or np.any(p.position > hi):
                        lo, hi = p.box_lo, p.box_hi
                self._er_box.append((lo, hi))
            self._er_amp = {}
            self._amb_order = 2
            self._C = (self._amb_order + 1) ** 2
            if self.hrtf is not None:
                # 2nd-order SH smooths the HRTF above ~2 kHz anyway: 3 ms of filter (interaural delay included)
                er_len = int(0.003 * fs)
                max_rel = int(np.ceil((self.hrtf.onsets.max() - self.hrtf.onsets.min()) * fs))
                self.er_nfft = 1 << int(np.ceil(np.log2(B + er_len + 16)))
                big = 1 << int(np.ceil(np.log2(self.taps + max_rel + 64)))
                self._er_filters, self._er_bulk = self.hrtf.ambisonic_filters(self._amb_order, max(big, self.er_nfft),
                                                                             er_len)
                if big > self.er_nfft:
                    h = np.fft.irfft(self._er_filters, big, axis=-1)[..., :er_len]
                    self._er_filters = np.fft.rfft(h, self.er_nfft, axis=-1).astype(np.complex64)
            else:
                self.er_nfft, self._er_bulk = 0, 0.0
                dec = np.zeros((2, self._C))
                dec[:, 0] = 0.5 if cfg.output == "stereo" else np.sqrt(0.5)
                if cfg.output == "stereo":
                    dec[:, 1] = [0.5 / np.sqrt(3), -0.5 / np.sqrt(3)]
                self._er_decode = dec.astype(np.float32)
            self.subsystems.append("early_reflections")
        self._late_on = cfg.late_reverb and self.probes is not None
        self.coupling, self._groups, self._modal = None, 1, False
        if self._late_on:
            self._probe_rt = np.array([p.rt60 for p in self.probes])
            self._probe_vol = np.array([p.volume for p in self.probes])
            self.subsystems.append("late_reverb")
            if graph is not None and scene.rooms:  # each room excites its neighbours through doors and walls
                from sonicverse_core.acoustics.coupling import room_coupling

                self.coupling = room_coupling(scene, graph, self.probes)
                self._src_room_at = np.full((0, 3), np.nan)
                self._src_room = np.zeros(0, np.int64)
                if len(scene.rooms) > 1:
                    self.subsystems.append("coupled_rooms")
            # late sends: 0 the listener's room (or rooms unknown), 1 + r from room r
            self._groups = len(self.coupling.rooms) + 1 if self.coupling is not None else 1
            # the tails: each probe's as baked, and, with coupled rooms, each probe's room with its doorways shut
            # (0.161 V / A_own): a room's decay with its doors as they are lies between the two
            self._tail_rt = self._probe_rt
            self._modal = (self.coupling is not None and cfg.reverb == "convolution"
                           and any(p.room is not None for p in self.probes))  # probes baked per room
            if self._modal:
                c = self.coupling
                self._probe_room = c.room_of(self._probe_pos[:, :2])
                shut, self._shut = [], np.arange(len(self.probes))  # the tail index of each probe's shut-door decay
                for k, r in enumerate(self._probe_room):
                    if r >= 0 and c.S_open[r] > 0:  # a room without openings has no shut-door tail of its own
                        self._shut[k] = len(self.probes) + len(shut)
                        shut.append(np.maximum(0.161 * c.V[r] / c.A[r], self._probe_rt[k]))
                self._tail_rt = np.vstack([self._probe_rt] + shut)
        max_delay = cfg.max_distance / SPEED_OF_SOUND + 0.01 + (self.hrtf.onsets.max() if self.hrtf else 0)
        if self._late_on:
            max_delay += MAX_MIXING_TIME  # the late send's pre-delay
        if self._er:
            max_delay += 3 * cfg.er_order * float(np.max([np.max(p.box_hi - p.box_lo) for p in self.probes])) \
                / SPEED_OF_SOUND
        self.hist = B * (int(np.ceil(max_delay * fs / B)) + 3)
        self.write = 0  # ring index of the next block's first sample
        self._cap = 0
        self._n = 0
        self._bank = np.zeros(1, np.float32)
        self._live_idx: list[int] = []
        self._alloc_sources(8)
        self._state: list[dict] = []
        self._ramp = ((np.arange(B) + 1) / B).astype(np.float32)
        self._ramp64 = (np.arange(B) + 1) / B
        self.blocks = 0
        self._rolloff = rolloff_params(cfg)

    def _alloc_sources(self, cap: int) -> None:
        def g(name, shape, dtype, fill=0):
            setattr(self, name, _grown(getattr(self, name, None), shape, dtype, fill))

        g("_pos", (cap, 3), np.float64)
        g("_fwd", (cap, 3), np.float64)
        self._fwd[self._cap:, 0] = 1.0
        g("_gain", (cap,), np.float64)
        g("_dir_alpha", (cap,), np.float64)
        g("_dir_sharp", (cap,), np.float64, 1.0)
        g("_off", (cap,), np.int64)
        g("_len", (cap,), np.int64, 1)
        g("_cursor", (cap,), np.int64)
        g("_loop", (cap,), bool)
        g("_live", (cap,), bool)
        g("_ring", (cap, getattr(self, "hist", 1)), np.float32)
        g("_spread_frac", (cap,), np.float64)  # spread / 360
        if getattr(self, "paths", None) is not None:
            self.paths.grow(None, cap)
        if getattr(self, "coupling", None) is not None:
            self._src_room_at = _grown(self._src_room_at, (cap, 3), np.float64, np.nan)
            self._src_room = _grown(self._src_room, (cap,), np.int64, -1)
        for st in getattr(self, "_state", []):
            self._grow_state(st, cap)
        self._cap = cap

    # --- setup ------------------------------------------------------------------------------------------------
    def add_source(self, signal=None, position=(0, 0, 0), loop=True, gain=1.0, live=False, attached_to=None,
                   sample_rate=None, directivity=0.0, sharpness=1.0, forward=(1, 0, 0), spread=0.0) -> Source:
        pos = np.asarray(position, float)
        if pos.shape != (3,) or not np.all(np.isfinite(pos)):
            raise PoseError(f"source position must be 3 finite numbers, got {position}")
        if not (0 <= directivity <= 1) or not (1 <= sharpness <= 100) or not (0 <= spread <= 360):
            raise ConfigError("directivity must be in [0, 1], sharpness in [1, 100], spread in [0, 360] degrees")
        if signal is not None:
            signal = np.asarray(signal, np.float32).ravel()
            if sample_rate is not None and sample_rate != self.cfg.sample_rate:
                from scipy.signal import resample_poly

                g = np.gcd(int(sample_rate), self.cfg.sample_rate)
                signal = resample_poly(signal, self.cfg.sample_rate // g, int(sample_rate) // g).astype(np.float32)
            if len(signal) == 0:
                raise ConfigError("a source signal must not be empty")
            if not np.all(np.isfinite(signal)):
                raise ConfigError("source signal contains NaN or infinite samples")
        elif not live:
            raise ConfigError("a source needs a signal or live=True")
        if attached_to is not None and (self.scene is None or all(o.name != attached_to for o in self.scene.objects)):
            raise ConfigError(f"cannot attach a source to '{attached_to}': no such object in the scene")
        i = self._n
        if i >= self._cap:
            self._alloc_sources(2 * self._cap)
        if signal is not None:
            self._off[i] = len(self._bank)
            self._len[i] = len(signal)
            self._bank = np.concatenate([self._bank, signal])
        self._cursor[i], self._loop[i], self._live[i] = 0, bool(loop), bool(live)
        self._dir_alpha[i], self._dir_sharp[i] = directivity, sharpness
        self._n += 1
        s = Source(self, i, live, attached_to)
        s.position, s.gain, s.forward = pos, float(gain), forward
        if live:
            self._live_idx.append(i)
        self._spread_frac[i] = spread / 360.0
        for st in self._state:
            st["fresh"][i] = True
            st["any_fresh"] = True
        self.sources.append(s)
        return s

    def add_listener(self, position=(0, 0, 1.5), yaw=0.0, pitch=0.0, exclude=()) -> Listener:
        """A listener; ``exclude``: sources it does not hear (e.g. the user's own microphone: no sidetone)."""
        lis = Listener(np.zeros(3))
        self.set_listener(lis, position, yaw, pitch)
        self.listeners.append(lis)
        B = self.cfg.block
        st = {"limit": 1.0, "scene_version": None, "any_fresh": True, "out": np.zeros((2, B)),
              "R": np.eye(3)}
        self._grow_state(st, self._cap)
        if self._er:
            st["er_tmp"] = np.zeros(B, np.float32)
            if self.hrtf is not None:
                from sonicverse_core.acoustics.fft import irfft_plan, rfft_plan

                st["er_hist"] = np.zeros((self._C, self.er_nfft), np.float32)
                st["er_fft"], st["er_A"] = rfft_plan(st["er_hist"])
                st["er_acc"] = np.zeros((2, self.er_nfft // 2 + 1), np.complex64)
                st["er_ifft"], st["er_y"] = irfft_plan(st["er_acc"], self.er_nfft)
            else:
                st["er_y"] = np.zeros((2, B), np.float32)
        if self._late_on:
            if self.cfg.reverb == "fdn":
                from sonicverse_core.acoustics.reverb import FDNReverb

                st["fdn"] = FDNReverb(self.cfg.sample_rate, self.cfg.block)
            else:
                from sonicverse_core.acoustics.reverb import ConvolutionReverb

                st["conv"] = ConvolutionReverb(self.cfg.sample_rate, self.cfg.block, self._tail_rt,
                                               groups=self._groups, **self._tail_colour())
                if self._modal:  # the coupled rooms' slowest mode: its own input (its shapes differ per group) and
                    # its own noise (tails of other seeds: the two add in energy, not in amplitude)
                    st["conv_slow"] = ConvolutionReverb(self.cfg.sample_rate, self.cfg.block, self._tail_rt,
                                                        seed=SLOW_SEED, groups=self._groups, **self._tail_colour())
                    st["ears"] = np.ones((2, self.cfg.block + 1), np.complex64)  # the slow tail's direction
                    st["portal"], st["portal_idx"] = None, -1
            st["late_level"] = None
            st["sends"] = np.zeros((self._groups, B), np.float32)
            st["seen"] = np.zeros(self._groups, bool)
            st["shapes"] = np.ones((self._groups, len(BANDS)))
            st["shapes_key"] = None
            if self.cfg.reverb == "fdn":
                st["mid"] = np.ones(self._groups, np.float32)
                st["mono"] = np.zeros(B, np.float32)
                st["fdn_out"] = np.zeros((2, B))
        self._state.append(st)
        for src in exclude:
            self.set_heard(lis, src, False)
        return lis

    def set_heard(self, lis: Listener, source: Source, heard: bool) -> None:
        """Whether ``lis`` hears ``source`` at all (direct, reflections and reverb)."""
        k = next(i for i, li in enumerate(self.listeners) if li is lis)
        self._state[k]["mute"][source.index] = not heard

    def _grow_state(self, st: dict, cap: int) -> None:
        K = self._K if getattr(self, "_er", False) else 0

        def grow(key, shape, dtype, fill=0):
            st[key] = _grown(st.get(key), shape, dtype, fill)

        grow("hist", (cap, 2, self.nfft), np.float32)
        grow("delay", (cap, 2), np.float64)
        grow("gain", (cap,), np.float64)
        grow("spec", (cap, 2, self.nf), np.complex64)
        grow("spec_new", (cap, 2, self.nf), np.complex64)
        for key, shape, dtype in (("dirs", (cap, 3), np.float64), ("dist", (cap,), np.float64),
                                  ("gain_new", (cap,), np.float64), ("amp", (cap, len(BANDS)), np.float32),
                                  ("delay0", (cap,), np.float64)):  # per-block geometry, written by the kernel
            grow(key, shape, dtype)
        st["acc"] = np.zeros((2, 2, self.nf), np.complex64)
        from sonicverse_core.acoustics.fft import irfft_plan

        st["both_fft"], st["both"] = irfft_plan(st["acc"], self.nfft)  # both filters' outputs, unnormalised
        grow("X", (cap, 2, self.nf), np.complex64)
        grow("curve", (cap, self.nf), np.float32)
        grow("delay_new", (cap, 2), np.float64)
        grow("tri", (cap, 3), np.int64)
        grow("w", (cap, 3), np.float64)
        grow("occ_moved", (cap,), np.float64)
        grow("group", (cap,), np.int64)
        grow("use_occ", (cap,), bool, True)
        st["ffts"] = {}  # forward plans over hist[:n], per source count n (the buffers above are new now)
        grow("occ", (cap, len(BANDS)), np.float64, 1.0)
        grow("occ_target", (cap, len(BANDS)), np.float64, 1.0)
        grow("occ_seg", (cap, 6), np.float64, np.nan)
        grow("fresh", (cap,), bool, True)
        grow("mute", (cap,), bool, False)
        if K:
            grow("er_delay", (cap, K), np.float64)
            grow("er_gain", (cap, K), np.float64)
            grow("er_Y", (cap, K, (2 + 1) ** 2), np.float64)
            grow("er_delay_new", (cap, K), np.float64)
            grow("er_gain_new", (cap, K), np.float64)
            grow("er_Y_new", (cap, K, (2 + 1) ** 2), np.float64)
            st["amb"] = np.zeros(((2 + 1) ** 2, self.cfg.block), np.float32)
        grow("send", (cap,), np.float64)
        grow("send_delay", (cap,), np.int64)
        if getattr(self, "paths", None) is not None:
            self.paths.grow(st, cap)

    @staticmethod
    def set_listener(lis: Listener, position, yaw, pitch=None) -> None:
        p = np.asarray(position, float)
        if p.shape != (3,) or not (math.isfinite(p[0]) and math.isfinite(p[1]) and math.isfinite(p[2])) or \
                not math.isfinite(yaw) or (pitch is not None and not math.isfinite(pitch)):
            raise PoseError(f"listener pose must be finite, got {position}, yaw {yaw}, pitch {pitch}")
        lis.position, lis.yaw = p, float(yaw)
        if pitch is not None:
            lis.pitch = float(pitch)

    # --- per block ---------------------------------------------------------------------------------------------
    def _advance_sources(self) -> None:
        n, B = self._n, self.cfg.block
        w0 = self.write
        if n == 0:
            self.write = (w0 + B) % self.hist
            return
        for s in self.sources:
            if s.attached_to is not None:
                self._pos[s.index] = self.scene.object(s.attached_to).sound_position()
        read_sources(self._bank, self._off[:n], self._len[:n], self._cursor[:n], self._loop[:n], self._gain[:n],
                     self._ring, w0, B)
        for i in self._live_idx:
            s = self.sources[i]
            row = self._ring[i, w0:w0 + B]
            if s.pending is None:
                row.fill(0.0)
            else:
                scale_into(s.pending, self._gain[i], row)
            s.pending = None
        self.write = (w0 + B) % self.hist

    def render_block(self, outs: list | None = None) -> list[np.ndarray]:
        """Advance one block; returns one (2, block) float32 array per listener: new arrays, or the ones in
        ``outs`` (one preallocated (2, block) float32 array per listener), written in place."""
        if not self.listeners:
            raise ConfigError("add a listener before rendering")
        self._advance_sources()
        res = outs if outs is not None else []
        for li, lis in enumerate(self.listeners):
            st = self._state[li]
            out = st["out"]
            out.fill(0.0)
            n = self._n
            if n:
                if self.occlusion is not None:
                    self.occlusion.update(st, self._pos[:n], lis.position)
                k = self.cfg.occlusion_smoothing if self.blocks else 0.0
                occ, target, fresh = st["occ"][:n], st["occ_target"][:n], st["fresh"][:n]
                pos, fwd = self._pos[:n], self._fwd[:n]
                if self.paths is not None:  # around corners, through doorways: one emitter per source still
                    self.paths.update(st, pos, lis.position)
                    target, pos, fwd = self.paths.apply(st, pos, fwd, lis.position, target, self._rolloff, k, fresh)
                    self.stats["paths"] = self.paths.stats["paths"]
                # smoothed towards the target; fresh sources jump; one this listener does not hear: no direct, ER
                # or late path
                smooth_toward(occ, target, k, fresh, st["mute"][:n])
                R = st["R"]
                head_rotation(lis.yaw, lis.pitch, R)
                self._direct(st, lis, R, occ, pos, fwd, out)
                if self._er:
                    self._early(st, lis, R, occ, pos, out)
                if self._late_on:
                    self._late(st, lis, st["dist"][:n], occ, out)
                if st["any_fresh"]:
                    fresh[:] = False
                    st["any_fresh"] = False
            if not all_finite(out):
                self._recover(st)
                out.fill(0.0)
            if outs is None:
                res.append(np.empty((2, self.cfg.block), np.float32))
            st["limit"] = limit(out, res[li], st["limit"], 0.05)
        self.blocks += 1
        return res

    def _ffts(self, st, n: int):
        """The forward plan over the first n sources' overlap-save histories (made once per source count)."""
        plan = st["ffts"].get(n)
        if plan is None:
            from sonicverse_core.acoustics.fft import Plan

            plan = st["ffts"][n] = Plan(st["hist"][:n], st["X"][:n])
        return plan

    def _direct(self, st, lis, R, occ, pos, fwd, out) -> None:
        """Every source's direct sound (or, without line of sight, its path: ``pos`` and ``fwd`` are the emitters'
        positions and forwards, ``occ`` their per-band amplitude), added into ``out``."""
        cfg, n, B = self.cfg, self._n, self.cfg.block
        dirs, dist, gain, amp, delay0 = (st[k][:n] for k in ("dirs", "dist", "gain_new", "amp", "delay0"))
        direct_geometry(pos, lis.position, R, fwd, self._dir_alpha[:n], self._dir_sharp[:n], occ, AIR_ABSORPTION,
                        *self._rolloff, SPEED_OF_SOUND, dirs, dist, gain, amp, delay0)
        curve = st["curve"][:n]
        np.matmul(amp, self._band_matrix, out=curve)  # (n, nf) smooth per-band curves
        spec, delay = st["spec_new"][:n], st["delay_new"][:n]
        if self.hrtf is not None:
            tri, w = self.hrtf.weights(dirs, cfg.hrtf_interpolation, out=(st["tri"][:n], st["w"][:n]))
            spread = self._spread_frac[:n]
            mix_spectra(self.hrtf.spectra(self.nfft), tri, w, curve, spread, self._diffuse_spectrum(), spec)
            onset_delays(w, tri, self.hrtf.onsets, delay0, spread, self._mean_onset(), delay)
        else:
            self._pan(dirs, curve, spec)
            if cfg.output == "stereo":  # an interaural time and level panner
                woodworth_delays(dirs, delay0, HEAD_RADIUS / SPEED_OF_SOUND, delay)
            else:
                np.copyto(delay, delay0[:, None])
        fresh = st["fresh"][:n]
        p_delay, p_gain, p_spec = st["delay"][:n], st["gain"][:n], st["spec"][:n]
        if st["any_fresh"]:
            p_delay[fresh], p_gain[fresh], p_spec[fresh] = delay[fresh], gain[fresh], spec[fresh]
        h = st["hist"][:n]
        shift_left(h.reshape(-1, self.nfft), B)
        gather(self._ring, self.write - B, p_delay, delay, float(cfg.sample_rate), p_gain[:, None], gain[:, None],
               h[:, :, -B:])  # (n, 2, B) fractional-delay taps, straight into the overlap-save input
        self._ffts(st, n).run()
        acc = st["acc"]
        changed = accumulate(st["X"][:n], spec, p_spec, acc[1], acc[0])
        st["both_fft"].run()  # (2 filters, 2 ears, nfft), unnormalised
        crossfade_into(st["both"], self._ramp, 1.0 / self.nfft, changed, out)
        np.copyto(p_delay, delay)
        np.copyto(p_gain, gain)
        st["spec"], st["spec_new"] = st["spec_new"], st["spec"]  # this block's filters become the previous ones

    def _pan(self, dirs, curve, spec) -> None:
        """Without HRTFs: constant-power panning by the lateral component (stereo; with Woodworth's interaural delay,
        :func:`woodworth_delays`) or sqrt(1/2) (mono)."""
        pan_spectra(dirs, curve, self.cfg.output == "mono", spec)

    def _mean_onset(self) -> np.ndarray:
        """The HRTF set's mean onset per ear (2,): a fully spread source's."""
        if getattr(self, "_onset_mean", None) is None:
            self._onset_mean = self.hrtf.onsets.mean(0)
        return self._onset_mean

    def _diffuse_spectrum(self) -> np.ndarray:
        """Power-average HRTF magnitude over all measured directions (2, nf), zero phase: the fully spread source."""
        if getattr(self, "_diffuse", None) is None:
            if self.hrtf is None:
                return np.zeros((2, self.nf), np.complex64)
            H = self.hrtf.spectra(self.nfft)
            self._diffuse = np.sqrt(np.mean(np.abs(H) ** 2, axis=0)).astype(np.complex64)
        return self._diffuse

    def _tail_colour(self) -> dict:
        """How the synthesised tails sound at the ears: binaural output takes the HRTF set's diffuse-field gains
        and interaural coherence per band; mono output the same tail in both channels; stereo two independent
        tails (both at the direct sound's sqrt(1/2) per channel). Computed once per renderer."""
        if getattr(self, "_colour", None) is None:
            if self.hrtf is not None:
                g, rho = self.hrtf.diffuse_field  # computed once per set (renderers share it)
                self._colour = {"gains": g, "coherence": rho}
            else:
                # the direct sound is panned with sqrt(1/2) per channel (constant power): so is the tail
                half = np.full((2, len(BANDS)), np.sqrt(0.5))
                self._colour = {"gains": half, "coherence": np.ones(len(BANDS)) if self.cfg.output == "mono" else None}
        return self._colour

    def _nearest_probe(self, st, p: np.ndarray) -> int:
        """The probe for the listener's early reflections: the nearest one in the listener's room (the nearest
        overall where the room is unknown or has none); cached per listener while it stays within 5 cm."""
        key = st.get("probe_key")
        if key is None or farther(key, p, 0.05):
            d2 = np.sum((self._probe_pos - p) ** 2, axis=1)
            if getattr(self, "coupling", None) is not None:  # the slice's room labels: a lookup, not polygon tests
                room = self.coupling.room_of(p[None, :2])[0]
                room = self.coupling.rooms[room] if room >= 0 else None
            else:
                room = self.scene.room_at(p[:2]) if self.scene is not None and self.scene.rooms else None
            same = np.array([r is not None and r is room for r in self._probe_rooms]) if room is not None else None
            if same is not None and same.any():
                d2 = np.where(same, d2, np.inf)
            st["probe_key"], st["probe"] = p.copy(), int(np.argmin(d2))
        return st["probe"]

    def _early(self, st, lis, R, occ, pos, out) -> None:
        """Image sources of the nearest probe's box, encoded in 2nd-order ambisonics, decoded binaurally, added into
        ``out``. ``pos``: the emitters (a source heard along a path is imaged from where its path puts it: outside
        the listener's room, it has no images, and its room's sound arrives by the coupled late reverb)."""
        cfg, n, B = self.cfg, self._n, self.cfg.block
        k = self._nearest_probe(st, lis.position)
        if k not in self._er_amp:
            self._er_amp[k] = image_amplitudes(self._refl[k], cfg.er_order)
        q, m, _ = lattice(cfg.er_order)
        delay, gain, Y = st["er_delay_new"][:n], st["er_gain_new"][:n], st["er_Y_new"][:n]
        lo, hi = self._er_box[k]
        image_taps(pos, lo, hi, q, m, self._er_amp[k], lis.position, R, *self._rolloff, occ, self._er_bulk,
                   SPEED_OF_SOUND, delay, gain, Y)
        fresh = st["fresh"][:n]
        pd, pg, pY = st["er_delay"][:n], st["er_gain"][:n], st["er_Y"][:n]
        if st["any_fresh"]:
            pd[fresh], pg[fresh], pY[fresh] = delay[fresh], gain[fresh], Y[fresh]
        amb = st["amb"]
        encode_taps(self._ring, self.write - B, pd, delay, float(cfg.sample_rate), pg, gain, pY, Y, self._ramp, amb,
                    st["er_tmp"])
        for a, b in (("er_delay", "er_delay_new"), ("er_gain", "er_gain_new"), ("er_Y", "er_Y_new")):
            st[a], st[b] = st[b], st[a]
        if self.hrtf is None:
            np.matmul(self._er_decode, amb, out=st["er_y"])
            add_tail(st["er_y"], 1.0, out)
            return
        h = st["er_hist"]
        shift_left(h, B)
        h[:, -B:] = amb
        st["er_fft"].run()
        accumulate_sh(st["er_A"], self._er_filters, st["er_acc"])
        st["er_ifft"].run()
        add_tail(st["er_y"], 1.0 / self.er_nfft, out)

    def _recover(self, st: dict) -> None:
        """A listener's block came out non-finite: clear every state that carries it into later blocks (filter
        histories, reflection history, reverb network, limiter), and any non-finite source history."""
        self.stats["recoveries"] += 1
        for key in ("hist", "acc", "er_hist", "er_acc", "amb"):
            if key in st:
                st[key][:] = 0
        for key in ("fdn", "conv", "conv_slow"):
            if key in st:
                st[key].reset()
        st["limit"], st["late_level"], st["late_key"] = 1.0, None, None
        bad = ~np.isfinite(self._ring)
        if bad.any():
            self._ring[bad] = 0.0

    def render(self, seconds: float) -> list[np.ndarray]:
        """Render ``seconds`` of audio: one (2, n) float32 array per listener."""
        blocks = int(np.ceil(seconds * self.cfg.sample_rate / self.cfg.block))
        outs = [[] for _ in self.listeners]
        for _ in range(blocks):
            for k, o in enumerate(self.render_block()):
                outs[k].append(o)
        return [np.concatenate(o, axis=1) for o in outs]
