"""A convolution tail's late part in long partitions, its work spread over the blocks (``RenderConfig.
tail_partitions="auto"``, the default where a tail spans 64 blocks or more).

A 3 s tail at 48 kHz is 563 partitions of a 256-frame block, and uniformly partitioned convolution multiplies every
one of them every block. Gardner (1995) keeps the first partitions short (the latency) and makes the later ones
long: here the first 2 L samples stay in partitions of one block (:class:`~sonicverse_core.acoustics.reverb.
ConvolutionReverb`'s own delay line) and the rest is cut into Q partitions of L = m blocks. A long partition's
input is a whole period (m blocks); its output is needed from 2 L after that period's start, so the m blocks of
the next period have time to compute it, and each does a share (as real-time convolvers do, Wefers 2015): the
first m / 4 transform the groups' sends (a few groups each), the middle ones multiply-accumulate a range of the
delay line's Q rows, the last m / 4 transform back into a second buffer. The following period plays the result out a block at a time, with
that block's mixing weights, late level and diffuse share, so the mix ramps exactly as the short partitions'.

The same convolution up to rounding where the sends are unshaped: tested against one-block partitions to -100 dB.
What differs, and by how little, is measured in ``tests/test_long_tail.py``:
- the groups' per-band shapes are applied to each period's spectrum over its 2 L bins (finer than one block's);
- a tail that enters the mix (the listener walks to another probe) is computed from the next period on: its part
  later than 2 L is missing until then (at the worst, one of two equal tails replaced by a third, the level is
  under 1 dB low for a period);
- the directional share's per-ear gains (a neighbouring room's doorway) are those of the block that starts the
  period's inverse transforms, so the part later than 2 L follows a head turn up to a period late.
Nothing is allocated per block: every buffer, plan and view is made here.
"""
from __future__ import annotations

import numpy as np

from sonicverse_core.acoustics.fft import Plan, band_bins
from sonicverse_core.acoustics.late_kernels import (fdl_fill, fdl_mac_add, long_close, long_play, long_take, pick_slots,
                                                    portal_curve)

SLOTS = 4  # tails a period computes at most: a listener mixes two probes, each between doors open and shut


class LongPartitions:
    """The long partitions of one :class:`~sonicverse_core.acoustics.reverb.ConvolutionReverb` (its ``long``):
    ``HL`` / ``HLd`` the tails' long spectra (2Q, 2 | 1, L + 1) (``HLd`` None: no directional channel); ``stagger``
    in [0, 1): where in the period this reverb does its transforms, so that a listener's several reverbs do not
    all transform in the same block."""

    def __init__(self, sample_rate: int, block: int, m: int, groups: int, HL, HLd=None, stagger: float = 0.0):
        self.B, self.m = B, m = block, m
        self.L = L = m * block
        self.Q = Q = len(HL[0]) // 2
        self.HL, self.HLd = HL, HLd
        nf = L + 1
        self.phase = int(stagger * m) % m
        self.t = 0
        G = groups
        self.col = np.zeros((G, L), np.float32)  # this period's sends, a block at a time
        self.frame = np.zeros((G, 2 * L), np.float32)  # [last period | this period], transformed group by group
        self.X = np.zeros((G, nf), np.complex64)
        self._fwd = [Plan(self.frame[g], self.X[g]) for g in range(G)]
        self.live_col, self.live_last, self.live = (np.zeros(G, bool) for _ in range(3))
        self.order = np.zeros(G, np.int64)  # the live groups first
        self.n_live = 0
        self.curves = np.ones((G, nf), np.float32)  # the groups' shapes over these bins (the reverb sets them)
        self.bins = band_bins(2 * L, sample_rate)
        self.fdl = np.zeros((Q, nf), np.complex64)
        self.j = 0  # periods closed
        self.slot, self.off = 0, Q - 1
        S = min(SLOTS, len(HL))
        self.acc = np.zeros((S, 2, nf), np.complex64)
        # outputs double-buffered: one is played while the other is computed (the inverse transforms are spread
        # over the period's last blocks, while its other blocks still play the older one)
        self.y = np.zeros((2, S, 2, 2 * L), np.float32)
        self._inv = [[Plan(self.acc[s], self.y[b, s], inverse=True) for s in range(S)] for b in range(2)]
        if HLd is not None:
            self.acc_d = np.zeros((S, 1, nf), np.complex64)
            self.Yd = np.zeros((S, 2, nf), np.complex64)
            self.yd = np.zeros((2, S, 2, 2 * L), np.float32)
            self._inv_d = [[Plan(self.Yd[s], self.yd[b, s], inverse=True) for s in range(S)] for b in range(2)]
            self.gains = np.zeros((2, nf), np.complex64)  # the directional share's per-ear gains over these bins
            self._gains_of = (None, -1)  # the ears (and their version) they were made for
            self._bins_own = self.bins.copy()  # a kernel's own (the shared one is read-only)
        self.play = 0  # the output buffer being played
        self.slot_of = np.full(S, -1, np.int64)  # the tail each slot computes this period
        self.ready = np.full(S, -1, np.int64)  # the tail whose output each slot plays this period
        self.dir_on = self.dir_ready = False
        self.quiet = Q + 1  # periods closed in a row without sound: past Q the delay line holds silence alone
        # the period's work, in about equal shares (a transform of 2 L samples costs about as much as a tenth of
        # the multiply-accumulate): the groups' transforms in phases [0, F), the multiply-accumulate's rows in [F,
        # m - F), the inverse transforms (each slot's own channels, then its directional ones) in [m - F, m)
        self.F = F = max(1, m // 4)
        edges = np.linspace(0, Q, m - 2 * F + 1).round().astype(np.int64)
        jobs = np.linspace(0, 2 * S, F + 1).round().astype(np.int64)
        self._work = [(0, 0)] * F + [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])] + \
            [(int(a), int(b)) for a, b in zip(jobs[:-1], jobs[1:])]
        self.scale = 1.0 / (2 * L)
        self._warm()

    def _warm(self) -> None:
        """Compile (or load) the per-block kernels now, on these buffers' types, changing nothing: one first called in
        a real-time callback would stall it for as long as numba takes (the reverb's own kernels likewise)."""
        long_close(self.frame, self.col, self.live_last, self.live_col, self.live, self.order)
        long_take(self.col[:, :self.B], self.col, 0, self.live_col, self.live_col)
        w = np.zeros(len(self.HL))
        pick_slots(w, w, self.slot_of)
        fdl_fill(self.X, self.curves, self.live, False, self.fdl[0])
        fdl_mac_add(self.fdl, self.HL[0], 0, 0, 0, self.acc[0])
        long_play(self.y, 0, 0, self.ready, w, w, 0.0, 0.0, 0.0, np.zeros((2, self.B)))
        if self.HLd is not None:
            long_play(self.yd, 0, 0, self.ready, w, w, 0.0, 0.0, 0.0, np.zeros((2, self.B)))
            fdl_mac_add(self.fdl, self.HLd[0], 0, 0, 0, self.acc_d[0])
            portal_curve(np.zeros((2, self.bins.shape[0])), 0.0, self._bins_own, self.gains)

    def reset(self) -> None:
        for a in (self.col, self.frame, self.fdl, self.y, self.live_col, self.live_last, self.live):
            a.fill(0)
        if self.HLd is not None:
            self.yd.fill(0)
        self.slot_of.fill(-1)
        self.ready.fill(-1)
        self.dir_on = self.dir_ready = False
        self.quiet = self.Q + 1

    def process(self, x, live, w0, w1, lv0, lv1, diffuse, ears, shaped, out, dacc) -> None:
        """One block: play this block's share of the last period's output into ``out`` (and the directional share
        into ``dacc`` when ``ears``), mixed with the tails' weights ramped from ``w0`` to ``w1`` and the late level
        from ``lv0`` to ``lv1``; take in the groups' sends ``x`` (G, B) (``live``: the groups with sound in this
        block or the last); do this block's share of the period's work."""
        m, F = self.m, self.F
        ph = (self.t + self.phase) % m
        self.t += 1
        start = self.L + ph * self.B  # this block's part of the last period's output (the valid half)
        long_play(self.y, self.play, start, self.ready, w0, w1, lv0, lv1, self.scale * diffuse, out)
        if self.dir_ready and ears is not None:
            long_play(self.yd, self.play, start, self.ready, w0, w1, lv0, lv1, self.scale, dacc)
        if ph == 0:  # the last period's sends are complete: this period computes their long partitions
            self.n_live = long_close(self.frame, self.col, self.live_last, self.live_col, self.live, self.order)
            self.quiet = 0 if self.n_live else min(self.quiet + 1, self.Q + 1)
            self.slot = self.j % self.Q
            self.off = self.Q - 1 - self.slot
            self.j += 1
            pick_slots(w0, w1, self.slot_of)
            self.dir_on = ears is not None and self.HLd is not None
            for s in range(len(self.slot_of)):
                if self.slot_of[s] >= 0:
                    self.acc[s].fill(0)
                    if self.dir_on:
                        self.acc_d[s].fill(0)
        long_take(x, self.col, ph * self.B, live, self.live_col)
        quiet = self.quiet > self.Q  # silence in every row of the delay line (the Q-th silent period zeroed the
        # last row that had sound): nothing to compute, nothing to play
        a, b = self._work[ph]
        if quiet:
            pass
        elif ph < F:
            for i in range(ph, self.n_live, F):
                self._fwd[self.order[i]].run()
            if ph == F - 1:
                fdl_fill(self.X, self.curves, self.live, shaped, self.fdl[self.slot])
        elif ph < m - F:
            for s in range(len(self.slot_of)):
                k = self.slot_of[s]
                if k >= 0 and b > a:
                    fdl_mac_add(self.fdl, self.HL[k], self.off, a, b, self.acc[s])
                    if self.dir_on:
                        fdl_mac_add(self.fdl, self.HLd[k], self.off, a, b, self.acc_d[s])
        else:
            self._inverse(a, b, ears, ph == m - F)
        if ph == m - 1:  # the period's outputs are complete: the next period plays them
            self.play = 1 - self.play
            if quiet:
                self.ready.fill(-1)
            else:
                np.copyto(self.ready, self.slot_of)
            self.dir_ready = self.dir_on and not quiet

    def _inverse(self, a: int, b: int, ears, first: bool) -> None:
        """Inverse transforms ``a``..``b`` - 1 of the period (j < S: slot j's own channels; S + j: its directional
        ones) into the buffer not being played; ``first``: the period's first (the directional gains are made)."""
        if first and self.dir_on:
            if ears is None:
                self.dir_on = False
            elif self._gains_of != (id(ears), ears.version):
                portal_curve(ears.band, ears.beta, self._bins_own, self.gains)
                self._gains_of = (id(ears), ears.version)
        S, w = len(self.slot_of), 1 - self.play
        for j in range(a, b):
            s = j % S
            if self.slot_of[s] < 0:
                continue
            if j < S:
                self._inv[w][s].run()
            elif self.dir_on:
                np.multiply(self.acc_d[s], self.gains, out=self.Yd[s])
                self._inv_d[w][s].run()
