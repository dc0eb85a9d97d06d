"""The late reverb, a subsystem of :class:`~sonicverse_core.acoustics.renderer.AcousticRenderer` (the renderer's
module docstring says what it does): the sends of every source to the listener's reverb, the probes' tails around
the listener, the rooms' coupling per band, and with probes baked per room the two coupled tails (the listener's
room's own decay and the slowest mode's)."""
from __future__ import annotations

import math

import numpy as np

from sonicverse_core.acoustics.direct import HEAD_RADIUS
from sonicverse_core.acoustics.fft import band_bins
from sonicverse_core.acoustics.kernels import farther, rows_moved
from sonicverse_core.acoustics.late_kernels import (buildup_filter, groups_sending, late_groups, late_send, mix_ramped,
                                                    tail_blend)
from sonicverse_core.acoustics.probes import SPEED_OF_SOUND
from sonicverse_core.acoustics.reverb import PortalEars
from sonicverse_core.acoustics.sources import grown
from sonicverse_core.acoustics.state import PerSource
from sonicverse_core.scene.materials import BANDS

MID = slice(4, 7)  # 500 Hz - 2 kHz
MAX_MIXING_TIME = 0.08  # s: the late tail starts at most this long after the direct sound
SLOW_SEED = 1000  # the slowest coupled mode's tails: noise independent of the rooms' own
SEED_STRIDE = 10_007  # RenderConfig.tail_seed's step between realisations (a tail per probe within a stride)
PORTAL_STEP = 5.0  # degrees: the azimuth table of the neighbouring room's direction
APART = 1.25  # a coupled mode is heard apart only if it decays this much slower than the listener's room alone
# blocks after a door's move before the late reverb takes the rooms' new balance: the move's occlusion and paths
# are cast in the block after it and the early reflections' walls in the next, so the late re-mix comes third
# (about 10 ms at 256 frames, inside the tail's own build-up) and no block carries two of them
DOOR_MIX_DELAY = 2


class NeighbourTail:
    """A coupled mode heard apart from the listener's room and the slowest mode (``RenderConfig.neighbour_tails``):
    its convolution (``conv``: the tails of the room it rings in, the own room's noise, which those tails never
    share with it), the per-ear gains of the direction it arrives from (``ears``, ``portal``, ``portal_idx``), its
    tail weights (``w``) and per-group amplitudes (``shapes``), the room (``room``; -1 idle), the coupled mode
    (``mode``) and whether its convolution still rings (``live``); ``key`` what its weights and amplitudes were made
    for, ``at`` where its direction was found (found again 10 cm on); ``buildup`` its sends' build-up (None: off).
    Its sends are its own (``LateState.sends_slow[1 + j]``): their distance law takes its mode's decay. With the
    FDN option (``RenderConfig.reverb="fdn"``) ``conv`` is None and ``fdn`` a network of its own, decaying as its
    mode, fed the groups' sends at their mid-band amplitudes (``mid``, made for ``fdn_key``), without a direction."""

    __slots__ = ("conv", "ears", "portal", "portal_idx", "w", "shapes", "room", "mode", "live", "key", "at",
                 "buildup", "fdn", "mid", "fdn_key")

    def __init__(self, conv, block: int, buildup=None, fdn=None, groups: int = 0):
        self.conv, self.ears, self.buildup, self.fdn = conv, PortalEars(block), buildup, fdn
        self.portal, self.portal_idx, self.w, self.shapes, self.room, self.live = None, -1, None, None, -1, False
        self.mode, self.key, self.at, self.fdn_key = -1, None, None, None
        self.mid = np.ones(groups, np.float32) if fdn is not None else None

    def reverb(self):
        """Its reverberator: the convolution or the FDN."""
        return self.conv if self.conv is not None else self.fdn


class LateState(PerSource):
    """A listener's late reverb: per source its send's gain and delay (``send``, ``send_delay``: ramped from) and,
    with rooms of their own, its sends' gains to the coupled modes heard apart (``send_slow``: the slowest, then
    each :class:`NeighbourTail`'s), the send it joins
    (``group``: 0 the listener's room or rooms unknown, 1 + r room r) and whether its send falls with the direct
    path's transmission (``use_occ``); per group the block's sends (``sends``; ``sends_slow`` (M, G, B) to the
    modes), the decays their distance laws take (``rt_send``; ``rt_slow`` (M, G), 0: an idle mode), which carry
    sound (``seen``) and their per-band
    amplitudes (``shapes``, made for ``shapes_key``); the reverberator (``conv`` and, with rooms of their own,
    ``conv_slow`` and its direction ``ears`` / ``portal``; or ``fdn``, and ``fdn_slow`` with rooms of their own);
    the probes' mix for where the listener stands (``params``, made at ``key``; its room ``lis_room``) and the level
    it was rendered at."""

    __slots__ = ("send", "send_delay", "send_slow", "group", "use_occ", "group_moved", "fdn", "conv", "conv_slow",
                 "ears", "portal", "portal_idx", "level", "sends", "seen", "shapes", "shapes_key", "mid", "mono",
                 "fdn_out", "key", "params", "lis_room", "room_reverbs", "gen", "modal_key", "modal_w", "modal_shapes",
                 "modal_wait",
                 "fdn_rt", "fdn_slow", "mid_own", "mid_slow", "fdn_key", "rt_send", "rt_slow", "sends_slow",
                 "buildup", "buildup_slow", "more", "qs", "vbuf")
    ROWS = (("send", (), np.float64, 0), ("send_delay", (), np.int64, 0), ("send_slow", (), np.float64, 0),
            ("group", (), np.int64, 0), ("use_occ", (), bool, True), ("group_moved", (), bool, False))

    def __init__(self, cap: int, groups: int, block: int, modes: int = 0):
        super().__init__(cap, tuple((n, (modes,), d, f) if n == "send_slow" else (n, sh, d, f)
                                    for n, sh, d, f in self.ROWS))
        self.fdn = self.conv = self.conv_slow = self.ears = self.portal = None
        self.mid = self.mono = self.fdn_out = self.fdn_rt = None
        self.fdn_slow = self.mid_own = self.mid_slow = self.fdn_key = None
        self.portal_idx = -1
        self.level = None
        self.buildup = self.buildup_slow = None  # TailBuildUp of other rooms' sends (RenderConfig.tail_buildup)
        self.more: list[NeighbourTail] = []  # coupled modes heard apart besides the slowest (a tail or network each)
        self.sends = np.zeros((groups, block), np.float32)
        self.rt_send = np.full(groups, 0.5)  # per group the decay its sends' distance law uses (late_send)
        self.rt_slow = np.full((modes, groups), 0.5)  # the same for the coupled modes' sends
        self.sends_slow = np.zeros((modes, groups, block), np.float32)  # the modes' sends (coupled rooms only)
        self.qs, self.vbuf = np.zeros((2, modes)), np.zeros(block, np.float32)  # late_send's scratch
        self.seen = np.zeros(groups, bool)
        self.shapes = np.ones((groups, len(BANDS)))
        self.shapes_key = self.key = self.params = self.modal_key = self.modal_w = self.modal_shapes = None
        self.lis_room, self.room_reverbs, self.gen = -1, 0, 0
        self.modal_wait = -1  # blocks left before a door's new balance is mixed in (-1: none pending)


class TailBuildUp:
    """The late part of a sound from another room builds up: the receiving room's late energy rises from nothing
    instead of starting at full level. Two parts (session 61):

    * a share ``beam`` (``RenderConfig.tail_beam``, 0.7) fills it as 1 - e^(-t / tau), tau =
      ``RenderConfig.tail_buildup`` (20 ms): energy that comes through a doorway arrives as a beam and fills the
      room over its first few reflections. A room fills faster than it empties: this tau is at most T' / 3 of the
      tail it feeds (T' = RT60 / 13.8; a dead room's own tail builds up in a few milliseconds);
    * the rest fills it at the coupled rooms' own rate (:meth:`set_slow`, per source room: ``coupling.late_split``'s
      ``buildup_tau``, 1 / (lam_1 - lam_0) of the two rooms' energy balance, 0.15 s for two 47 m^3 rooms joined by a
      doorway, 6 ms for a dead room beside a live one; at most ``TAU_MAX``). Until it is set, that part fills at
      the first part's rate.

    The diffuse build-up alone (all at the balance's rate) makes the early decay as long as the peer's and C50 4-10
    dB low; the beam alone makes the early decay 25% short (``bench fidelity``'s two rooms; README). The sends of
    the other rooms' groups (1 + r, r not the listener's room) pass through K taps per part spread over 0-3 tau,
    each at a fixed delay jittered within its interval so that the taps do not comb; tap k carries the share of
    e^(-t / tau) / tau that falls in its interval. The shares sum to 1: the energy that crosses is the rooms' energy
    balance's, only later (so the late level after the build-up is higher: by about tau / T' for the beam's part,
    under 1 dB in the homes). The sends' last 3 ``TAU_MAX`` are kept per group; nothing is allocated per block."""

    K = 8
    TAU_MAX = 0.3  # s: the slowest build-up (rooms joined through a third or by a wall alone are capped here)

    def __init__(self, tau: float, fs: float, groups: int, block: int, beam: float = 1.0):
        self.tau, self.fs, self.beam = tau, fs, beam
        u = np.linspace(0.0, 3.0, self.K + 1)  # the taps' intervals in units of tau
        e = np.exp(-u)
        share = (e[:-1] - e[1:]) / (e[0] - e[-1])
        self._at = u[:-1] + np.random.default_rng(7).uniform(0.0, 1.0, self.K) * (u[1] - u[0])  # fixed jitter
        self.two = beam < 1.0
        self.share = np.r_[beam * share, (1.0 - beam) * share] if self.two else share
        self.delay = np.zeros((groups, len(self.share)), np.int64)
        self.gain = np.sqrt(self.share).astype(np.float32)
        self._g = np.zeros(self.K)
        self.rt = self._te = None
        self.slow = None  # the second part's tau per group (s); None: the first part's
        self.L = int(np.round(self._at.max() * max(tau, self.TAU_MAX if self.two else 0.0) * fs)) + 1
        self.hist = np.zeros((groups, self.L + block), np.float32)  # a ring per group: the last L samples and this block
        self.pos = 0  # where this block goes in the rings
        self._acc = np.zeros(block)

    def _taps(self, rt60: float) -> None:
        """The first part's delays (and the second's while it has no time of its own) for a tail of ``rt60``; the
        second part's own delays are set by :meth:`set_slow` alone (they do not depend on the tail)."""
        te = min(self.tau, max(rt60, 0.05) / 13.8155 / 3.0)
        if te == self._te:  # a tail of 0.83 s or more: the beam's time is tail_buildup whatever the decay
            return
        self._te = te
        np.multiply(self._at, te * self.fs, out=self._g)
        np.round(self._g, out=self._g)
        self.delay[:, :self.K] = self._g
        if self.two and self.slow is None:
            self.delay[:, self.K:] = self._g

    def set_slow(self, tau: np.ndarray) -> None:
        """The second part's build-up time per group (G,) in s (0 for a group that does not build up), capped at
        ``TAU_MAX``. Called when the doors or the listener's room change, not per block."""
        if self.two:
            self.slow = np.clip(np.asarray(tau, float), 0.0, self.TAU_MAX)
            self.delay[:, self.K:] = np.round(np.outer(self.slow, self._at) * self.fs)

    def process(self, sends: np.ndarray, lis_room: int, rt60: float) -> None:
        """Filter ``sends`` (G, B) in place: every group but the listener's own room's (0, and 1 + lis_room);
        ``rt60``: the mid-band decay (s) of the tail they feed. Allocates nothing."""
        if self.rt != rt60:
            self.rt = rt60
            self._taps(rt60)
        self.pos = buildup_filter(sends, self.hist, self.pos, self.delay, self.gain,
                                  1 + lis_room if lis_room >= 0 else 0, self._acc)

    def reset(self) -> None:
        self.hist[:] = 0.0
        self.pos = 0


class LateReverb:
    """The late-reverb subsystem of ``renderer`` (:mod:`sonicverse_core.acoustics.state`; the renderer's module
    docstring says what it does). ``graph``: the scene's path graph, for the rooms' coupling (None: rooms unknown,
    one send for every source)."""

    name = "late"

    def __init__(self, renderer, graph=None):
        self.r = r = renderer
        cfg, scene = r.cfg, r.scene
        self.door_delay = DOOR_MIX_DELAY  # blocks (0: the re-mix in the block that renders the move)
        self.rt = np.array([p.rt60 for p in r.probes])
        self.vol = np.array([p.volume for p in r.probes])
        r.coupling, self.groups, self.modal = None, 1, False
        if graph is not None and scene.rooms:  # each room excites its neighbours through doors and walls
            from sonicverse_core.acoustics.coupling import room_coupling

            r.coupling = room_coupling(scene, graph, r.probes)
            self._src_room_at = np.full((0, 3), np.nan)
            self._src_room = np.zeros(0, np.int64)
            self._probe_room = r.coupling.room_of(r._probe_pos[:, :2])
        # late sends: 0 the listener's room (or rooms unknown), 1 + r from room r
        self.groups = len(r.coupling.rooms) + 1 if r.coupling is not None else 1
        # the tails: each probe's as baked, and, with coupled rooms, each probe's room with its doorways shut
        # (0.161 V / A_own): a room's decay with its doors as they are lies between the two
        self.tail_rt = self.rt
        self.tail_edt = np.array([p.edt for p in r.probes]) if cfg.tail_edt else None
        self.modal = r.coupling is not None and any(p.room is not None for p in r.probes)  # probes baked per room
        if self.modal:
            c = r.coupling
            shut, self._shut = [], np.arange(len(r.probes))  # the tail index of each probe's shut-door decay
            for k, room in enumerate(self._probe_room):
                if room >= 0 and c.S_open[room] > 0:  # a room without openings has no shut-door tail of its own
                    self._shut[k] = len(r.probes) + len(shut)
                    shut.append(np.maximum(0.161 * c.V[room] / c.A[room], self.rt[k]))
            self.tail_rt = np.vstack([self.rt] + shut)
            if self.tail_edt is not None:  # a shut-door tail: one slope
                self.tail_edt = np.vstack([self.tail_edt] + shut)
        self._colour = None
        self._portal_table = None
        self._room_probes: dict = {}  # a room's probes (the re-mix's tails), found once
        self._portal_D = (None, 0.0)  # _portal's absorption and couplings at 1 kHz for (door state, listener's room)
        self._apart_key, self._apart_val = None, ()  # _apart's answer for (coupling state, listener's room)
        self._listeners = 0  # listener states made (their reverbs' long partitions are staggered)

    # --- the subsystem protocol ----------------------------------------------------------------------------------
    def state(self, cap: int) -> LateState:
        cfg = self.r.cfg
        # rooms beyond two: the modes that ring in yet other rooms, each heard apart
        extra = max(min(cfg.neighbour_tails, len(self.r.coupling.rooms) - 2), 0) if self.modal else 0
        # the coupled modes' sends (the slowest, then each neighbour tail's): their distance law takes their decay
        st = LateState(cap, self.groups, cfg.block, modes=1 + extra if self.modal else 0)
        buildup = cfg.tail_buildup > 0 and self.groups > 1  # other rooms' sends build up (rooms known)

        def build_up():
            return TailBuildUp(cfg.tail_buildup, float(cfg.sample_rate), self.groups, cfg.block,
                               beam=cfg.tail_beam if self.modal else 1.0) if buildup else None

        st.buildup = build_up()
        if self.modal:
            st.buildup_slow = build_up()
        if cfg.reverb == "fdn":
            from sonicverse_core.acoustics.reverb import FDNReverb

            st.fdn = FDNReverb(cfg.sample_rate, cfg.block)
            st.mid = np.ones(self.groups, np.float32)
            st.mono = np.zeros(cfg.block, np.float32)
            st.fdn_out = np.zeros((2, cfg.block))
            if self.modal:  # a second network: the slowest coupled mode; one more per neighbour's mode
                st.fdn_slow = FDNReverb(cfg.sample_rate, cfg.block)
                st.mid_own = np.ones(self.groups, np.float32)
                st.mid_slow = np.ones(self.groups, np.float32)
                st.more = [NeighbourTail(None, cfg.block, build_up(), fdn=FDNReverb(cfg.sample_rate, cfg.block),
                                         groups=self.groups) for _ in range(extra)]
        else:
            from sonicverse_core.acoustics.reverb import ConvolutionReverb

            seed = cfg.tail_seed * SEED_STRIDE
            part = {"partitions": cfg.tail_partitions}
            # each reverb transforms its long partitions in other blocks of the period than the listener's other
            # reverbs and than the other listeners' (those render in the same callback: robots)
            at = (self._listeners * 0.381966) % 1.0  # the golden section: listeners spread over the period
            self._listeners += 1
            st.conv = ConvolutionReverb(cfg.sample_rate, cfg.block, self.tail_rt, seed=seed, groups=self.groups,
                                        probe_edts=self.tail_edt, stagger=at, **part, **self.tail_colour())
            if self.modal:  # the coupled rooms' slowest mode: its own input (its shapes differ per group) and
                # its own noise (tails of other seeds: the two add in energy, not in amplitude)
                st.conv_slow = ConvolutionReverb(cfg.sample_rate, cfg.block, self.tail_rt, seed=SLOW_SEED + seed,
                                                 probe_edts=self.tail_edt, groups=self.groups,
                                                 direct=cfg.output != "mono", direct_seed=seed,
                                                 stagger=(at + 0.5) % 1.0,
                                                 **part, **self.tail_colour())
                st.ears = PortalEars(cfg.block)  # the slow tail's direction
                # rooms beyond two: the modes that ring in yet other rooms, each heard from its doorway. Their
                # tails are those rooms' own, so the own-room noise serves (the same partitions, cached). The
                # directional channels are shared with the slow tail's: each plays another room's tail
                st.more = [NeighbourTail(ConvolutionReverb(cfg.sample_rate, cfg.block, self.tail_rt, seed=seed,
                                                           probe_edts=self.tail_edt, groups=self.groups,
                                                           direct=cfg.output != "mono", direct_seed=seed,
                                                           stagger=(at + (0.25, 0.75, 0.125, 0.375)[j]) % 1.0, **part,
                                                           **self.tail_colour()),
                                         cfg.block, build_up())
                           for j in range(extra)]
        return st

    def grow(self, st: LateState | None, cap: int) -> None:
        if st is not None:
            st.grow(cap)
        elif self.r.coupling is not None:  # the room each source is in, and where it was found
            self._src_room_at = grown(self._src_room_at, (cap, 3), np.float64, np.nan)
            self._src_room = grown(self._src_room, (cap,), np.int64, -1)

    def max_delay(self) -> float:
        return self.r.direct.max_delay() + MAX_MIXING_TIME  # the send's pre-delay

    def reset(self, st: LateState) -> None:
        for rev in (st.fdn, st.fdn_slow, st.conv, st.conv_slow, st.buildup, st.buildup_slow,
                    *(t.reverb() for t in st.more), *(t.buildup for t in st.more)):
            if rev is not None:
                rev.reset()
        st.level, st.key, st.fdn_key = None, None, None

    def render(self, st: LateState, ls, lis, out) -> None:
        """The late reverb of every source, added into ``out``."""
        n = ls.n
        self._late(st, lis, ls.direct.dist[:n], ls.occ[:n], ls.fresh[:n], out)

    def tail_colour(self) -> dict:
        """How the synthesised tails sound at the ears: binaural output takes the HRTF set's diffuse-field gains
        and interaural coherence per band; mono output the same tail in both channels; stereo two independent
        tails (both at the direct sound's sqrt(1/2) per channel). Computed once per renderer."""
        if self._colour is None:
            if self.r.hrtf is not None:
                g, rho = self.r.hrtf.diffuse_field  # computed once per set (renderers share it)
                self._colour = {"gains": g, "coherence": rho}
            else:
                # the direct sound is panned with sqrt(1/2) per channel (constant power): so is the tail
                half = np.full((2, len(BANDS)), np.sqrt(0.5))
                self._colour = {"gains": half,
                                "coherence": np.ones(len(BANDS)) if self.r.cfg.output == "mono" else None}
        return self._colour

    def _late(self, st, lis, dist, occ, fresh, out) -> None:
        """The late reverb of every source, added into ``out``."""
        cfg, n, B = self.r.cfg, self.r._n, self.r.cfg.block
        key = st.key
        if key is None or farther(key, lis.position, 0.01):  # probe interpolation, per centimetre moved
            w = 1 / np.maximum(np.linalg.norm(self.r._probe_pos - lis.position, axis=1), 0.1) ** 2
            if self.r.coupling is not None:  # the listener's own room's probes (its neighbours come by coupling)
                st.lis_room = int(self.r.coupling.room_of(lis.position[None, :2])[0])
                if st.lis_room >= 0:
                    mine = self._probe_room == st.lis_room
                    if mine.any():
                        w = np.where(mine, w, 0.0)
            if len(w) > 2:  # the two nearest probes: each one mixed in costs a convolution per block
                w[np.argsort(w)[:-2]] = 0.0
            w /= w.sum()
            rt = w @ self.rt
            vol = float(w @ self.vol)
            if self.r.coupling is not None and st.lis_room >= 0 and self.r.coupling.V[st.lis_room] > 1:
                # the room's own volume (a proxy box sees through doors; the coupling's V is max(volume, 1), made
                # once: a Room's volume is a polygon's area computed on every call)
                vol = float(self.r.coupling.V[st.lis_room])
            lo, hi = float(np.mean(rt[3:6])), float(rt[7])  # 250 Hz-1 kHz and 4 kHz: the FDN's two fit points
            # diffuse-field level relative to the direct sound at 1 m: 16 pi / A, A = 0.161 V / T (Sabine)
            level = np.sqrt(16 * np.pi * max(lo, 0.05) / (0.161 * max(vol, 1.0)))
            t_mix = float(np.clip(np.sqrt(max(vol, 0.0)) / 1000.0, 0.005, MAX_MIXING_TIME))  # Polack: sqrt(V) ms
            st.key, st.params = lis.position.copy(), (w, lo, hi, level, t_mix)
            st.room_reverbs = int(np.count_nonzero(w > 1e-4))  # tails convolved for this listener
            st.gen = st.gen + 1  # the listener moved: the modal mix is made again
        w, lo, hi, level, t_mix = st.params
        if self.modal and st.lis_room >= 0:
            self._late_modal(st, lis, dist, occ, fresh, w, lo, t_mix, out)
            return
        # Barron & Lee 1988: the late level falls with source distance; a source behind walls excites the
        # coupled space: the send keeps the square root of the direct path's mid-band transmission
        group, use_occ, shapes = self._late_groups(st, n)
        self.r.stats["room_reverbs"] = st.room_reverbs
        sends = st.sends
        st.rt_send.fill(lo)  # one decay for the whole space
        late_send(self.r._ring, (self.r.write - B) % self.r.hist, dist, occ, use_occ, group, st.rt_send, st.send[:n],
                  st.send_delay[:n], fresh, sends, float(cfg.sample_rate), SPEED_OF_SOUND, t_mix, st.rt_slow,
                  st.send_slow[:n], st.sends_slow[:0], st.qs, st.vbuf)
        self.r.stats["rooms_sending"] = groups_sending(group, st.send[:n], st.seen)
        if st.buildup is not None:
            st.buildup.process(sends, st.lis_room, lo)
        lv0 = st.level if st.level is not None else level
        st.level = level
        if st.fdn is not None:
            old = st.fdn_rt
            if old is None or abs(old[0] - lo) > 0.002 * lo or abs(old[1] - hi) > 0.002 * hi:  # 0.2 %
                st.fdn.set_rt60(lo, hi)
                st.fdn_rt = (lo, hi)
            np.matmul(st.mid, sends, out=st.mono)  # the groups' mid-band couplings
            add = st.fdn.process(st.mono, out=st.fdn_out)
            mix_ramped(add, 1.0, 1.0, lv0, level, 1.0, out)
            return
        if len(w) < len(self.tail_rt):  # the shut-door tails play no part outside the rooms
            w = np.r_[w, np.zeros(len(self.tail_rt) - len(w))]
            st.params = (w, lo, hi, level, t_mix)
        st.conv.process(sends, w, shapes, out=out, level=(lv0, level), shapes_key=st.shapes_key)

    def _late_modal(self, st, lis, dist, occ, fresh, w, lo, t_mix, out) -> None:
        """The late reverb of coupled rooms (``coupling.late_split``): each source room's send, shaped per band,
        feeds the listener's own room's decay (its probes' tails, blended between doors open and shut as the room's
        decay with its doors as they are) and the slowest mode's (the tails of the room it rings in); the energies
        are the rooms' statistical energy balance, no Sabine level."""
        n, B = self.r._n, self.r.cfg.block
        c, lr = self.r.coupling, st.lis_room
        group, use_occ, _ = self._late_groups(st, n)
        split = c.late_split()
        key = (split["gen"], st.gen)
        if st.modal_key == key:  # (the doors back as they were before a pending re-mix: none pending)
            st.modal_wait = -1
        elif st.modal_key is not None and st.modal_key[0] != key[0] and self.door_delay > 0:
            # a door moved: its occlusion, paths and early reflections go first (DOOR_MIX_DELAY); the tails play
            # on with the balance before it meanwhile (a listener who changes rooms meanwhile waits as well)
            if st.modal_wait < 0:
                st.modal_wait = self.door_delay
            if st.modal_wait > 0:
                st.modal_wait -= 1
                key = st.modal_key
        if st.modal_key != key:
            st.modal_wait = -1
            st.modal_w, st.modal_shapes = self._modal_mix(st, lis, w, split, lr)
            st.modal_key = key
            # a source in another room: Barron's distance law with the slower of its room's and the listener's
            # room's own decays (the energy that crosses dies out as slowly as that), not the listener's alone:
            # a dead room beside a live one hears the live one, and the live one hears the dead one
            own = split["own_rt"][:, 3:6].mean(1)
            np.maximum(own, own[lr], out=st.rt_send[1:])
            st.rt_send[0] = lo
            # the slowest mode's share dies out as slowly as that mode before it reaches the listener: a source in
            # a dead room beside a live one rings on in the live one, not at the dead room's decay
            np.maximum(st.rt_send, float(np.mean(split["slow_rt"][3:6])), out=st.rt_slow[0])
            for j, t in enumerate(st.more, 1):  # a neighbour's mode: its own decay (0: idle, no sends)
                if t.room >= 0:
                    np.maximum(st.rt_send, float(np.mean(split["modes_rt"][t.mode, 3:6])), out=st.rt_slow[j])
                else:
                    st.rt_slow[j] = 0.0
            if st.buildup is not None:  # how fast the listener's room fills from each other room
                slow = np.r_[0.0, split["buildup_tau"][:, lr]]
                for b in (st.buildup, st.buildup_slow, *(t.buildup for t in st.more)):
                    if b is not None:
                        b.set_slow(slow)
            st.room_reverbs = int(np.count_nonzero(st.modal_w[0] > 1e-4) + np.count_nonzero(st.modal_w[1] > 1e-4)
                                  + sum(np.count_nonzero(t.w > 1e-4) for t in st.more if t.room >= 0))
        self.r.stats["room_reverbs"] = st.room_reverbs
        sends = st.sends
        late_send(self.r._ring, (self.r.write - B) % self.r.hist, dist, occ, use_occ, group, st.rt_send,
                  st.send[:n], st.send_delay[:n], fresh, sends, float(self.r.cfg.sample_rate), SPEED_OF_SOUND, t_mix,
                  st.rt_slow, st.send_slow[:n], st.sends_slow, st.qs, st.vbuf)
        self.r.stats["rooms_sending"] = groups_sending(group, st.send[:n], st.seen)
        if st.buildup is not None:  # the slow mode's share rings on in the source's room: it builds up as well
            st.buildup.process(sends, lr, lo)
            st.buildup_slow.process(st.sends_slow[0], lr, st.rt_slow[0, 0])  # the slowest mode's decay, >= lo
        if st.fdn is not None:
            self._fdn_modal(st, split, lr, sends, lo, out)
            return
        (w_own, w_slow), (sh_own, sh_slow) = st.modal_w, st.modal_shapes
        st.conv.process(sends, w_own, sh_own, out=out, shapes_key=key)
        st.conv_slow.process(st.sends_slow[0], w_slow, sh_slow, out=out, shapes_key=key,
                             ears=self._portal_ears(st, lis))
        for j, t in enumerate(st.more, 1):  # the other rooms' modes heard apart: their own sends and shapes
            if t.live:
                if t.buildup is not None:
                    t.buildup.process(st.sends_slow[j], lr, max(st.rt_slow[j, 0], lo))
                t.conv.process(st.sends_slow[j], t.w, t.shapes, out=out, shapes_key=t.key,
                               ears=self._portal_ears(t, lis))
                t.live = t.room >= 0  # an idle tail ramps to silence in one block, then stops

    def _fdn_modal(self, st, split, lr, sends, lo, out) -> None:
        """The FDN option with rooms of their own: one network decaying as the listener's room does with its doors
        as they are, one as the slowest mode and one per neighbour's mode heard apart (:meth:`_apart`), each fed the
        rooms' sends at their mid-band amplitudes of the energy balance (the cheap option: two decay times per
        network, no per-band shapes, the other rooms' tails without a direction). A neighbour's network left idle
        rings out, then stops."""
        if st.fdn_key != st.modal_key:  # the doors or the listener moved: new decays and amplitudes
            own, slow = split["own_rt"][lr], split["slow_rt"]
            st.fdn.set_rt60(float(np.mean(own[3:6])), float(own[7]))
            st.fdn_slow.set_rt60(float(np.mean(slow[3:6])), float(slow[7]))
            sh_own, sh_slow = st.modal_shapes
            st.mid_own[:] = sh_own[:, MID].mean(1)
            st.mid_slow[:] = sh_slow[:, MID].mean(1)
            st.fdn_key = st.modal_key
        for fdn, mid, x in ((st.fdn, st.mid_own, sends), (st.fdn_slow, st.mid_slow, st.sends_slow[0])):
            np.matmul(mid, x, out=st.mono)
            np.add(out, fdn.process(st.mono, out=st.fdn_out), out=out)
        for j, t in enumerate(st.more, 1):
            if not t.live:
                continue
            if t.room >= 0 and t.fdn_key != t.key:  # woken, or the doors or the listener's room changed
                rt = split["modes_rt"][t.mode]
                t.fdn.set_rt60(float(np.mean(rt[3:6])), float(rt[7]))
                t.mid[:] = t.shapes[:, MID].mean(1)
                t.fdn_key = t.key
            if t.buildup is not None:
                t.buildup.process(st.sends_slow[j], lr, max(st.rt_slow[j, 0], lo))
            np.matmul(t.mid, st.sends_slow[j], out=st.mono)
            add = t.fdn.process(st.mono, out=st.fdn_out)
            np.add(out, add, out=out)
            if t.room < 0 and max(float(add.max()), -float(add.min())) < 1e-7:  # idle and rung out: stop
                t.live, t.fdn_key = False, None
                t.fdn.reset()

    def _portal_ears(self, st, lis):
        """A tail's direction when it rings in another room (``st``: the late state for the slow tail, or a
        :class:`NeighbourTail`): the share ``beta`` arriving from where it enters (the doorway, ``_modal_mix``), with
        that direction's level differences and interaural delay for the head as it is turned now (a table row per
        5 degrees of azimuth; the gains are made again only when the row changes: nothing allocated while the head
        turns); a :class:`PortalEars`."""
        portal = st.portal
        if portal is None:
            return None
        (px, py), beta = portal
        p = lis.position
        az = math.degrees(math.atan2(py - p[1], px - p[0])) - lis.yaw
        idx = int(round(az / PORTAL_STEP)) % len(self._portal_table)
        if idx != st.portal_idx:
            st.ears.set(self._portal_table[idx], beta, self._portal_bins, self._portal_delays[idx])
            st.portal_idx = idx
        return st.ears

    def _portal_tables(self):
        """(A, 2, 9) per-band ear gains of azimuths k x 5 degrees in the horizontal plane over the diffuse field's,
        normalised to a mean power of 1 over the two ears (binaural: the HRTF set; stereo: the constant-power
        panner), and (9, block + 1) the bands' weights over the convolution's bins; None for mono output."""
        if self._portal_table is not None or self.r.cfg.output == "mono":
            return
        az = np.radians(np.arange(0.0, 360.0, PORTAL_STEP))
        if self.r.hrtf is not None:
            n = 1 << int(np.ceil(np.log2(max(4096, 2 * self.r.hrtf.taps))))
            H, _ = self.r.hrtf.lookup_spectra(np.c_[np.cos(az), np.sin(az), np.zeros(len(az))], n)
            f = np.fft.rfftfreq(n, 1 / self.r.cfg.sample_rate)
            diffuse = self.r.hrtf.diffuse_field[0]
            ratio = np.ones((len(az), 2, len(BANDS)))
            for b, fc in enumerate(BANDS):
                sel = (f >= fc / np.sqrt(2)) & (f < fc * np.sqrt(2))
                if sel.any():
                    ratio[:, :, b] = np.sqrt(np.mean(np.abs(H[:, :, sel]) ** 2, axis=2)) / diffuse[None, :, b]
        else:  # the stereo panner: constant power by the lateral component (left ear towards +y)
            s = np.sin(az)
            ratio = np.repeat(np.stack([np.sqrt(1 + s), np.sqrt(np.maximum(1 - s, 0.0))], 1)[:, :, None],
                              len(BANDS), axis=2)
        ratio /= np.sqrt(np.mean(ratio ** 2, axis=1, keepdims=True))
        # the interaural delay of each azimuth on the far ear, in samples: Woodworth's, with the stereo panner's head
        # (the direct sound's ITD without HRTFs; KEMAR's largest, 0.65-0.7 ms, is about its 0.66 ms)
        lat = np.arcsin(np.clip(np.sin(az), -1.0, 1.0))  # the lateral angle, + to the left (+y at yaw 0)
        itd = HEAD_RADIUS / SPEED_OF_SOUND * (lat + np.sin(lat)) * self.r.cfg.sample_rate
        self._portal_delays = np.rint(np.stack([np.maximum(-itd, 0.0), np.maximum(itd, 0.0)], 1)).astype(np.int64)
        self._portal_table = ratio
        self._portal_bins = band_bins(2 * self.r.cfg.block, self.r.cfg.sample_rate).copy()  # a kernel's own

    def _portal(self, lis, room, lr):
        """Where room ``room`` (a mode's) is heard from when it is not the listener's: the last bend of the open path
        from its probe (the doorway), the probe itself in sight or through a wall; and the share of that room's
        energy arriving straight from there rather than diffused in the listener's room: x / (1 + x),
        x = D / (4 pi r^2), D the listener's room's absorption plus its couplings at 1 kHz, r the distance (an
        aperture of the coupling's area radiating the neighbour's diffuse field). None for the listener's own
        room or mono output."""
        if room == lr or self.r.cfg.output == "mono":
            return None
        self._portal_tables()
        c = self.r.coupling
        mine = self._probes_of(room)
        if len(mine) == 0:
            return None
        xy = lis.position[:2]
        src = self.r._probe_pos[mine[np.argmin(np.sum((self.r._probe_pos[mine, :2] - xy) ** 2, axis=1))], :2]
        res = c.graph.path(src, xy)
        pt = res.last if res is not None else src
        r = max(float(np.hypot(*(pt - xy))), 0.5)
        key = (c, c.scene.dynamic_version, lr)  # the doors and the listener's room decide D, not a step
        if self._portal_D[0] != key:
            self._portal_D = (key, float(c.A[lr, 5] + c.coupling()[lr, :, 5].sum()))
        x = self._portal_D[1] / (4 * np.pi * r * r)
        return (float(pt[0]), float(pt[1])), x / (1 + x)

    def _probes_of(self, room: int) -> np.ndarray:
        """The indices of room ``room``'s probes (found once per room)."""
        mine = self._room_probes.get(room)
        if mine is None:
            mine = self._room_probes[room] = np.flatnonzero(self._probe_room == room)
        return mine

    def _modal_mix(self, st, lis, w, split, lr):
        """Tail weights (own, slow) over ``self.tail_rt`` and per-group per-band amplitudes (own, slow) (G, 9)."""
        P = len(self.r.probes)
        rt = self.tail_rt

        def blend(room, rt_now, weights, single=False):
            """Amplitude weights over the tails for ``room``'s probes (energy ``weights``), blended between doors
            open and shut so that the mid-band RT is ``rt_now``, and the blend's energy per band
            (:func:`tail_blend`)."""
            mine = self._probes_of(room)
            out, e = np.empty(len(rt)), np.empty(len(BANDS))
            tail_blend(rt, mine, self._shut, np.asarray(weights, float), float(np.mean(rt_now[MID])), single,
                       MID.start, MID.stop, out, e)
            return out, e

        d2 = np.sum((self.r._probe_pos - lis.position) ** 2, axis=1)
        near = 1 / np.maximum(d2, 0.01)
        w_own, e_own = blend(lr, split["own_rt"][lr], np.asarray(w[:P], float) ** 2)
        w_slow, e_slow = blend(split["slow_room"], split["slow_rt"], near)
        E, f = split["energy"][:, lr], split["slow"][:, lr]  # (R_s, 9)
        own = np.sqrt(np.maximum(E * (1 - f), 0.0) / np.maximum(e_own, 1e-9))
        slow = np.sqrt(np.maximum(E * f, 0.0) / np.maximum(e_slow, 1e-9))
        sh_own, sh_slow = np.empty((self.groups, len(BANDS))), np.empty((self.groups, len(BANDS)))
        sh_own[0], sh_own[1:] = own[lr], own
        sh_slow[0], sh_slow[1:] = slow[lr], slow
        st.portal, st.portal_idx = self._portal(lis, split["slow_room"], lr), -1
        own_e = E * (1 - f)
        for t, (k, room) in zip(st.more, self._apart(st, split, lr)):  # other rooms' modes heard apart
            if room < 0:
                if t.room >= 0:  # fades out in its next block
                    t.w = np.zeros(len(rt))
                t.room, t.key = -1, None
                continue
            f_k = split["modes_share"][k][:, lr]
            own_e = own_e - E * f_k
            mine = self._probes_of(room)
            key = (split["gen"], lr, k, int(mine[np.argmax(near[mine])]))
            if t.key != key:  # the doors, the listener's room or the nearest probe changed, not a step
                t.w, e_k = blend(room, split["modes_rt"][k], near, single=True)
                amp = np.sqrt(np.maximum(E * f_k, 0.0) / np.maximum(e_k, 1e-9))
                t.shapes = np.empty((self.groups, len(BANDS)))
                t.shapes[0], t.shapes[1:] = amp[lr], amp
                if t.room < 0 and not t.live:  # woken: no history from an earlier room
                    t.reverb().reset()
                    if t.buildup is not None:
                        t.buildup.reset()
                t.room, t.mode, t.live, t.key, t.at = room, k, True, key, None
            if t.at is None or farther(t.at, lis.position, 0.1):  # its doorway, found again every 10 cm
                t.portal, t.portal_idx, t.at = self._portal(lis, room, lr), -1, lis.position.copy()
        if any(t.room >= 0 for t in st.more):
            own = np.sqrt(np.maximum(own_e, 0.0) / np.maximum(e_own, 1e-9))
            sh_own[0], sh_own[1:] = own[lr], own
        return (w_own, w_slow), (sh_own, sh_slow)

    def _apart(self, st, split, lr) -> list:
        """Which coupled modes besides the slowest the listener hears apart, as (mode, room) pairs (room -1: none),
        one per :class:`NeighbourTail`: modes that ring in another room than the listener's and the slowest mode's
        (one per room) and decay at least ``APART`` times slower than the listener's room alone, the ones that
        bring the most energy into the listener's room first (rooms near in the coupling, not in metres)."""
        if not st.more:
            return []
        key = (split["gen"], lr, len(st.more))  # the doors and the listener's room decide it, not a step
        if self._apart_key == key:
            return list(self._apart_val)
        taken = {lr, int(split["slow_room"])}
        own_mid = float(np.mean(split["own_rt"][lr, MID]))
        E = split["energy"][:, lr, MID].mean(1)  # (R_s,)
        cands = []
        for k in range(1, len(split["modes_rt"])):
            room = int(split["modes_room"][k])
            if room in taken or float(np.mean(split["modes_rt"][k, MID])) < APART * own_mid:
                continue
            if not np.any(self._probe_room == room):
                continue
            cands.append((float(np.max(E * split["modes_share"][k][:, lr, MID].mean(1))), k, room))
        best: dict = {}
        for score, k, room in sorted(cands, reverse=True):  # one mode per room: the one bringing the most
            if room not in best and score > 0:
                best[room] = (k, room)
        chosen = list(best.values())[:len(st.more)]
        self._apart_key, self._apart_val = key, tuple(chosen + [(-1, -1)] * (len(st.more) - len(chosen)))
        return list(self._apart_val)

    def _late_groups(self, st, n: int):
        """Per source, which send it joins (0: the listener's room, or rooms unknown; 1 + r: room r, filtered by
        its coupling to the listener's room) and whether its send falls with the direct path's transmission (rooms
        unknown); the groups' per-band amplitudes (G, 9), rewritten (and ``st.shapes_key`` changed) only when
        the listener's room or the coupling changes."""
        group, use_occ = st.group[:n], st.use_occ[:n]
        lr = st.lis_room
        if self.r.coupling is None or lr < 0:
            group.fill(0)
            use_occ.fill(True)
            if st.shapes_key != -1:
                st.shapes[:] = 1.0
                st.shapes_key = -1
                if st.mid is not None:
                    st.mid[:] = 1.0
            return group, use_occ, st.shapes
        c, pos = self.r.coupling, self.r._pos[:n]
        moved = st.group_moved
        if rows_moved(self._src_room_at[:n], pos, 0.05, moved[:n]):
            idx = np.flatnonzero(moved[:n])
            self._src_room[idx] = c.room_of(pos[idx, :2])
            self._src_room_at[idx] = pos[idx]
        late_groups(self._src_room[:n], lr, group, use_occ)
        key = (c.scene.dynamic_version, lr)  # the transfer changes with the doors only
        if st.shapes_key != key:
            st.shapes[1:] = c.transfer()[:, lr]  # the reverb transforms only the groups with sound
            st.shapes[0] = 1.0
            st.shapes_key = key
            if st.mid is not None:
                st.mid[:] = st.shapes[:, MID].mean(1)
        return group, use_occ, st.shapes
