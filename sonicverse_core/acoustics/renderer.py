"""The block renderer: N sources, one or more listeners, (2, block) float32 binaural output per listener.

The renderer owns the sources (their history ring and per-source arrays) and the listeners; the work of a block
is done by its subsystems, one protocol for all (:mod:`~sonicverse_core.acoustics.state`: per-listener typed state,
grow, maximum delay, render, reset), built by :func:`build_subsystems`, which leaves out what the scene does not
need: occlusion (``occlusion.py``), paths (``paths.py``), the direct sound (``direct.py``), early reflections
(``early.py``), late reverb (``late.py``).

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
  energy balance through doors and walls), one send per room, filtered per band; another room's send builds up
  (``late.TailBuildUp``): a share ``RenderConfig.tail_beam`` (0.7) over ``RenderConfig.tail_buildup`` (20 ms), as
  a doorway's beam fills the listener's room over a few reflections, the rest at the two rooms' own rate
  (``coupling.late_split``'s ``buildup_tau``, 0.15 s for two 47 m^3 rooms and a doorway). Each source's send is delayed
  by its travel time plus the mixing time (sqrt(V) ms, Polack), so the tail starts after the direct sound and the
  early reflections, and falls with distance (Barron). With probes baked per room (``BakeConfig.per_room``, the
  default) and convolution, each send feeds two tails instead, on independent noise: the listener's room's own
  decay (its tails with doors open and shut, blended as its doors are) and the coupled rooms' slowest mode, with
  the energies of the rooms' energy balance in time (:meth:`RoomCoupling.late_split`): a dead room beside a live
  one decays with two slopes. A slowest mode ringing in another room is heard from its doorway, in part (the
  level differences of that direction; ``late.LateReverb._portal``). With three rooms or more, up to
  ``RenderConfig.neighbour_tails`` (default 1) further modes ringing in yet other rooms, each decaying at least
  1.25 times slower than the listener's room alone, are heard apart as well: one tail each (the nearest probe of
  that room), from that room's doorway, chosen by the energy they bring into the listener's room
  (``late.LateReverb._apart``); a hall between two live rooms hears each of them decay as itself. Each mode heard
  apart has sends of its own, whose distance law takes that mode's decay. The FDN option (``reverb="fdn"``) gives
  each mode heard apart a network of its own, without a direction. A door's move reaches the late reverb's mix
  ``late.DOOR_MIX_DELAY`` blocks after the block that casts its occlusion and paths (the early reflections' walls
  are cast in the one between), so that a real-time stream meets the door's work one part a block.
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
from sonicverse_core.acoustics.direct import HEAD_RADIUS  # noqa: F401 - re-exported: the stereo panner's head
from sonicverse_core.acoustics.kernels import (all_finite, distance_gains, head_rotation, limit, read_sources,
                                               scale_into, smooth_toward)
from sonicverse_core.acoustics.late import LateReverb
from sonicverse_core.acoustics.occlusion import Occlusion, may_occlude
from sonicverse_core.acoustics.sources import Listener, Source, grown as _grown
from sonicverse_core.acoustics.state import ListenerState
from sonicverse_core.errors import ConfigError, PoseError


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


def build_subsystems(r) -> list:
    """The subsystems of renderer ``r`` in block order (:mod:`sonicverse_core.acoustics.state`), each also set as
    ``r.occlusion``, ``r.paths``, ``r.direct``, ``r.early``, ``r.late`` (None when left out), with their names
    added to ``r.subsystems``. What the scene does not need is left out: occlusion without geometry that can occlude
    (or with ``occlusion`` off), paths where the ear-height slice has no corner to go round, reflections and reverb
    without probes of an enclosed space (none for an open scene or one whose every surface absorbs everything:
    :func:`~sonicverse_core.acoustics.probes.scene_probes` gives it none); the rooms' coupling where the scene has
    more than one room."""
    from sonicverse_core.acoustics.direct import Direct

    cfg, scene = r.cfg, r.scene
    parts = []
    r.occlusion = r.paths = r.early = r.late = None
    graph = None
    if cfg.occlusion and scene is not None and may_occlude(scene):
        r.occlusion = Occlusion(scene, cfg.occlusion_tolerance, cfg.occlusion_rays_per_block)
        r.stats = r.occlusion.stats  # its ray counts are the renderer's
        r.subsystems.append("occlusion")
        parts.append(r.occlusion)
        if cfg.paths or cfg.late_reverb and scene.rooms:
            from sonicverse_core.acoustics.paths import path_graph

            graph = path_graph(scene, cfg.path_cell, caster=r.occlusion.caster)
        if cfg.paths and graph is not None and len(graph.nodes):  # a scene with no corner to go round needs none
            from sonicverse_core.acoustics.paths import Paths

            r.paths = Paths(graph, cfg.diffraction, cfg.occlusion_tolerance, cfg.occlusion_rays_per_block,
                            r._rolloff)
            r.subsystems.append("paths")
            parts.append(r.paths)
    r.direct = Direct(r)
    parts.append(r.direct)
    if cfg.early_reflections and r.probes is not None:
        from sonicverse_core.acoustics.early import EarlyReflections

        r.early = EarlyReflections(r)
        r.subsystems.append("early_reflections")
        parts.append(r.early)
    if cfg.late_reverb and r.probes is not None:
        r.late = LateReverb(r, graph)
        r.subsystems.append("late_reverb")
        if r.coupling is not None and len(scene.rooms) > 1:
            r.subsystems.append("coupled_rooms")
        parts.append(r.late)
    geometry = {"occlusion", "paths"}
    r._stages = ([(i, p) for i, p in enumerate(parts) if p.name in geometry],
                 [(i, p) for i, p in enumerate(parts) if p.name not in geometry])
    return parts


class AcousticRenderer:
    """The block renderer (the module's docstring). Its subsystems (:mod:`sonicverse_core.acoustics.state`) are
    ``parts``, each listener's state a :class:`~sonicverse_core.acoustics.state.ListenerState`."""

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
        self.stats = {"occlusion_rays": 0, "occlusion_skipped": 0}
        self.probes = [p for p in (probes or []) if p.enclosed > 0.5] or None
        if self.probes:
            self._probe_pos = np.array([p.position for p in self.probes])
        self.coupling = None
        self._rolloff = rolloff_params(cfg)
        self.parts = build_subsystems(self)  # leaves out what the scene does not need
        self.stats.update(paths=0, room_reverbs=0, rooms_sending=0)
        self.stats.update(nonfinite_input=0, recoveries=0)
        self.hist = B * (int(np.ceil(max(p.max_delay() for p in self.parts) * fs / B)) + 3)
        self.write = 0  # ring index of the next block's first sample
        self._cap = 0
        self._n = 0
        self._bank = np.zeros(1, np.float32)
        self._live_idx: list[int] = []
        self._alloc_sources(8)
        self._state: list[ListenerState] = []
        self._ramp = ((np.arange(B) + 1) / B).astype(np.float32)
        self._ramp64 = (np.arange(B) + 1) / B
        self.blocks = 0

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
        for part in self.parts:  # what subsystems keep per source for every listener
            part.grow(None, cap)
        for ls in getattr(self, "_state", []):
            ls.grow(cap)
            for part, st in zip(self.parts, ls.parts):
                part.grow(st, cap)
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
        for ls in self._state:
            ls.fresh[i] = True
            ls.any_fresh = True
        self.sources.append(s)
        return s

    def add_listener(self, position=(0, 0, 1.5), yaw=0.0, pitch=0.0, exclude=()) -> Listener:
        """A listener; ``exclude``: sources it does not hear (e.g. the user's own microphone: no sidetone)."""
        lis = Listener(np.zeros(3))
        self.set_listener(lis, position, yaw, pitch)
        self.listeners.append(lis)
        ls = ListenerState(self._cap, self.cfg.block)
        ls.parts = tuple(part.state(self._cap) for part in self.parts)
        for part, st in zip(self.parts, ls.parts):
            setattr(ls, part.name, st)
        self._state.append(ls)
        for src in exclude:
            self.set_heard(lis, src, False)
        return lis

    def set_heard(self, lis: Listener, source: Source, heard: bool) -> None:
        """Whether ``lis`` hears ``source`` at all (direct, reflections and reverb)."""
        k = next(i for i, li in enumerate(self.listeners) if li is lis)
        self._state[k].mute[source.index] = not heard

    def set_doors(self, fractions: dict) -> None:
        """Move the scene's doors (name -> open fraction) and build what the next block needs for them (the
        occlusion's geometry), as a real-time caller does between blocks; the next blocks render the move (its
        occlusion and paths, then the early reflections' walls, then the late mix: ``late.DOOR_MIX_DELAY``)."""
        for name, f in fractions.items():
            self.scene.set_door(name, float(f))
        if self.occlusion is not None:
            self.occlusion.prepare()

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
        geometry, sound = self._stages
        for li, lis in enumerate(self.listeners):
            ls = self._state[li]
            out = ls.out
            out.fill(0.0)
            n = ls.n = self._n
            if n:
                ls.smoothing = k = self.cfg.occlusion_smoothing if self.blocks else 0.0
                ls.pos, ls.fwd, ls.target = self._pos[:n], self._fwd[:n], ls.occ_target[:n]
                for i, part in geometry:  # occlusion, paths: what the sound stages hear each source through
                    part.render(ls.parts[i], ls, lis, out)
                # smoothed towards the target; fresh sources jump; one this listener does not hear: no direct, ER
                # or late path
                smooth_toward(ls.occ[:n], ls.target, k, ls.fresh[:n], ls.mute[:n])
                head_rotation(lis.yaw, lis.pitch, ls.R)
                for i, part in sound:  # direct, early reflections, late reverb
                    part.render(ls.parts[i], ls, lis, out)
                if self.paths is not None:
                    self.stats["paths"] = self.paths.stats["paths"]
                if ls.any_fresh:
                    ls.fresh[:n] = False
                    ls.any_fresh = False
            if not all_finite(out):
                self._recover(ls)
                out.fill(0.0)
            if outs is None:
                res.append(np.empty((2, self.cfg.block), np.float32))
            ls.limit = limit(out, res[li], ls.limit, 0.05)
        self.blocks += 1
        return res

    def warm_kernels(self) -> int:
        """Compile (or load from numba's cache) every kernel a block can reach, now rather than in a real-time
        callback, where one costs 0.1-3 s and the audio server drops the client. Renders a block with every listener
        at each probe (each room's own early reflections; the other rooms' sources along their paths and through the
        coupled reverb) and at a spot in no room (where a probe box's images apply), 2 + ``late.DOOR_MIX_DELAY``
        with every door moved (walls and room images cast again, the late reverb re-mixed) and one with the doors
        back, then one per door state a user's moves reach (every open/shut combination where the kept
        ``DOOR_STATES`` hold them all, else each door moved alone) and one with the doors back, so that their path
        graphs and coupled rooms' balances are made here, not in the block after a user opens a door; then puts the
        listeners back and clears every listener's state as on a fresh start. Returns the blocks rendered. The live
        audio workers call it before their stream opens (``app.audio_rt``)."""
        if not self.listeners:
            return 0
        saved = [(lis.position.copy(), lis.yaw, lis.pitch) for lis in self.listeners]
        stats = dict(self.stats)
        spots = [saved[0][0]]
        if self.probes:  # every probe (each room), and a spot in no room (a doorway, a wall: a probe box's images)
            spots = list(self._probe_pos) + [self._probe_pos.min(axis=0) - (5.0, 5.0, 0.0)]
        silence = np.zeros(self.cfg.block, np.float32)
        n = 0
        for p in spots:
            for lis in self.listeners:
                lis.position = np.array(p, float)
            for i in self._live_idx:  # a live source's block goes through its own path
                self.sources[i].pending = silence
            self.render_block()
            n += 1
        doors = self.scene.doors if self.scene is not None else []
        if doors:
            for lis in self.listeners:  # in a room (its probe's): every part a door's move reaches runs
                lis.position = np.array(spots[0], float)
            names, was = [d.name for d in doors], [d.open_fraction for d in doors]
            flip = [0.0 if f > 0.5 else 1.0 for f in was]
            self.set_doors(dict(zip(names, flip)))
            from sonicverse_core.acoustics.late import DOOR_MIX_DELAY

            for _ in range(2 + DOOR_MIX_DELAY):  # the move is cast in the block after it, the late re-mix later
                self.render_block()
                n += 1
            self.set_doors(dict(zip(names, was)))
            self.render_block()  # the doors' return is cast and the path graph refreshed here, not in the next block
            n += 1
            from sonicverse_core.acoustics.paths import DOOR_STATES

            # the door states a user's moves reach, met here (the path graph and the coupled rooms keep DOOR_STATES):
            # every open/shut combination where they all fit, else each door moved alone
            if 2 ** len(doors) <= DOOR_STATES:
                states = [[flip[k] if (m >> k) & 1 else was[k] for k in range(len(doors))]
                          for m in range(1, 2 ** len(doors))]
            else:
                states = [[flip[k] if k == j else was[k] for k in range(len(doors))] for j in range(len(doors))]
            for state in states + [was]:
                self.set_doors(dict(zip(names, state)))
                self.render_block()
                n += 1
        for lis, (p, yaw, pitch) in zip(self.listeners, saved):
            lis.position, lis.yaw, lis.pitch = p, yaw, pitch
        for ls in self._state:
            for part, st in zip(self.parts, ls.parts):
                part.reset(st)
            ls.fresh[:] = True
            ls.any_fresh = True
            ls.limit = 1.0
        self.stats.clear()
        self.stats.update(stats)
        return n

    def _recover(self, ls: ListenerState) -> None:
        """A listener's block came out non-finite: clear every state that carries it into later blocks (filter
        histories, reflection history, reverb network, limiter), and any non-finite source history."""
        self.stats["recoveries"] += 1
        for part, st in zip(self.parts, ls.parts):
            part.reset(st)
        ls.limit = 1.0
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
