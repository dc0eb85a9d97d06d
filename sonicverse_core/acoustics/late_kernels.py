"""The late reverb's compiled kernels (numba, cached on disk, GIL released; each has a NumPy twin in
``tests/test_late_kernels.py``, the glue's in ``tests/test_kernels.py``): the feedback delay network's per-sample
loop, the sends to the reverb and their build-up from other rooms, the partitioned convolution's frequency-domain
steps, the coupled rooms' groups and the neighbouring room's per-ear curve."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from sonicverse_core.acoustics.kernels import _fast, _opts, _wrap_copy


@njit(**_opts)
def fdn_process(x, out, buf, pos, delays, b0, p, z, cl, cr, norm, y):
    """One block of an N-line FDN with a Householder feedback matrix and one-pole damping per line.
    buf (N, size) ring; pos: write index; z (N,) filter states; y (N,) scratch. Returns the new write index."""
    N, size = buf.shape
    B = len(x)
    h = 2.0 / N
    inj = 1.0 / np.sqrt(N)
    for t in range(B):
        s = 0.0
        o0 = 0.0
        o1 = 0.0
        for k in range(N):
            v = buf[k, (pos - delays[k]) % size]
            o0 += cl[k] * v
            o1 += cr[k] * v
            zz = b0[k] * v + p[k] * z[k]
            if abs(zz) < 1e-25:
                zz = 0.0
            z[k] = zz
            y[k] = zz
            s += zz
        s *= h
        for k in range(N):
            buf[k, pos] = y[k] - s + x[t] * inj
        pos = (pos + 1) % size
        out[0, t] = o0 * norm
        out[1, t] = o1 * norm
    return pos


@njit(**_opts)
def buildup_filter(sends, hist, pos, delay, gain, skip, acc):
    """The other rooms' sends through the build-up's taps, in place (``late.TailBuildUp``): sends (G, B); hist
    (G, W): a ring of each group's sends, this block written from column ``pos`` on (wrapping at W); out[g, t] =
    sum_k gain[k] x[g, t - delay[g, k]] (delay (G, K) <= W - B: each group its own taps) for every group but 0 and
    ``skip`` (the listener's own room's), summed in float64 over k in order. Nothing is moved: each tap reads its B
    samples in at most two runs (a history copied to the front every few blocks cost 3 times the taps with a 0.9 s
    history). acc (B,) float64 scratch. Returns the next block's ``pos``."""
    G, B = sends.shape
    W = hist.shape[1]
    n1 = min(B, W - pos)  # this block's samples before the ring wraps
    for g in range(G):
        h = hist[g]
        for t in range(n1):
            h[pos + t] = sends[g, t]
        for t in range(n1, B):
            h[pos + t - W] = sends[g, t]
        if g == 0 or g == skip:
            continue
        for t in range(B):
            acc[t] = 0.0
        for k in range(len(gain)):
            a = gain[k]  # float32 x float32, then summed in float64, as the per-sample loop did
            s0 = pos - delay[g, k]
            if s0 < 0:
                s0 += W
            m = min(B, W - s0)
            for t in range(m):
                acc[t] += a * h[s0 + t]
            for t in range(m, B):
                acc[t] += a * h[s0 + t - W]
        for t in range(B):
            sends[g, t] = acc[t]
    pos += B
    return pos - W if pos >= W else pos


@njit(**_opts)
def _ring_fade(row, s0, s1, v):
    """v[t] = row[(s0 + t) mod H] (1 - r) + row[(s1 + t) mod H] r, r = (t + 1) / B: a crossfade between two read
    positions of a ring, in runs between either position's wrap (:func:`kernels._wrap_copy` reads one)."""
    B, H = len(v), len(row)
    j0, j1 = s0 % H, s1 % H
    t = 0
    while t < B:
        m = min(B - t, H - j0, H - j1)
        x0 = row[j0:j0 + m]
        x1 = row[j1:j1 + m]
        y = v[t:t + m]
        for k in range(m):
            r = (t + k + 1) / B
            y[k] = x0[k] * (1.0 - r) + x1[k] * r
        t += m
        j0 = (j0 + m) % H
        j1 = (j1 + m) % H


@njit(**_opts)
def late_send(ring, w0, dist, occ, use_occ, group, rt_group, p_send, p_delay, fresh, out, fs, c_sound, t_mix,
              rt_modes, p_modes, out_modes, qs, v):
    """Sends to the late reverb, one per group of sources (out (G, B): the groups are the rooms the sources are in,
    which the renderer filters by their coupling to the listener's room): per source, its dry samples delayed by
    its travel time plus the mixing time (ring[i, w0 + t - D], D = round((dist / c + t_mix) fs): the tail starts
    after the direct sound and the early reflections; when D changes, the old and the new delay are crossfaded
    across the block, so a teleport sends no step into the reverb), scaled by 10^(-0.174 r / T / 20) (Barron & Lee:
    the late level falls with distance) x 10^(-3 t_mix / T) (the decay before the tail starts), T the decay of the
    source's group (rt_group (G,): the listener's room's for group 0; for a source in another room the slower of
    its room's and the listener's, which the caller sets), and, where the
    rooms are unknown (use_occ), by the square root of the mid-band transmission of the direct path; ramped from
    p_send. p_send and p_delay (int64) are updated.

    With coupled rooms, out_modes (K, G, B) gets the same sends once per coupled mode heard apart (k = 0 the
    slowest, then the neighbouring rooms' modes), each mode's energy dying out at its own decay T = rt_modes[k,
    group] over the same time (ramped from p_modes[i, k], updated; rt_modes[k, 0] <= 0: mode k idle, its sends
    ramp to silence); an empty out_modes (0, G, B): none. qs (2, K) float64 and v (B,) float32: scratch."""
    B = out.shape[1]
    H = ring.shape[1]
    K = out_modes.shape[0]
    out[:] = 0.0
    for k in range(K):
        out_modes[k, :, :] = 0.0
    q, q0 = qs[0], qs[1]
    for i in range(len(dist)):
        T = max(rt_group[group[i]], 0.05)
        s = 10.0 ** (-0.174 * dist[i] / T / 20.0 - 3.0 * t_mix / T)
        a = 1.0
        if use_occ[i]:
            o = 0.0
            for b in range(4, 7):
                o += occ[i, b]
            a = np.sqrt(max(o / 3.0, 0.0))
        elif occ[i, 4] == 0.0 and occ[i, 5] == 0.0 and occ[i, 6] == 0.0:
            a = 0.0  # a source this listener does not hear
        s *= a
        any_q = False
        for k in range(K):
            if rt_modes[k, 0] <= 0.0:
                q[k] = 0.0
            else:
                Ts = max(rt_modes[k, group[i]], 0.05)
                q[k] = a * 10.0 ** (-0.174 * dist[i] / Ts / 20.0 - 3.0 * t_mix / Ts)
            q0[k] = q[k] if fresh[i] else p_modes[i, k]
            p_modes[i, k] = q[k]
            any_q = any_q or q[k] != 0.0 or q0[k] != 0.0
        D = np.int64((dist[i] / c_sound + t_mix) * fs + 0.5)
        s0 = s if fresh[i] else p_send[i]
        D0 = D if fresh[i] else p_delay[i]
        p_send[i] = s
        p_delay[i] = D
        if s == 0.0 and s0 == 0.0 and not any_q:
            continue
        g = group[i]
        if D0 == D:
            _wrap_copy(ring[i], w0 - D, np.float32(1.0), v)
        else:
            _ring_fade(ring[i], w0 - D0, w0 - D, v)
        ds = (s - s0) / B
        for t in range(B):
            out[g, t] += v[t] * np.float32(s0 + ds * (t + 1))
        for k in range(K):
            if q[k] != 0.0 or q0[k] != 0.0:
                dq = (q[k] - q0[k]) / B
                for t in range(B):
                    out_modes[k, g, t] += v[t] * np.float32(q0[k] + dq * (t + 1))


@njit(**_fast)
def fdl_mac(fdl, H, off, out):
    """Partitioned convolution's frequency-domain multiply-accumulate: Y[e, f] = sum_p fdl[p, f] H[off + p, e, f]
    (fdl (P, F) the input spectra, newest last in the circular order that ``off`` selects; H (2P, E, F) the tail's
    partitions, doubled so that no index wraps). The inverse FFT is the caller's; out (E, F) is overwritten."""
    P, F = fdl.shape
    E = out.shape[0]
    out[:] = 0
    for p in range(P):
        for e in range(E):
            for f in range(F):
                out[e, f] += fdl[p, f] * H[off + p, e, f]


@njit(**_opts)
def mix_ramped(y, w0, w1, lv0, lv1, scale, out):
    """out[e, t] += scale y[e, N - B + t] (w0 + (w1 - w0) r) (lv0 + (lv1 - lv0) r), r = (t + 1) / B: a probe's tail
    with its ramped mixing weight and the ramped late level."""
    E, B = out.shape
    off = y.shape[1] - B
    for t in range(B):
        r = (t + 1) / B
        g = scale * (w0 + (w1 - w0) * r) * (lv0 + (lv1 - lv0) * r)
        for e in range(E):
            out[e, t] += g * y[e, off + t]


@njit(**_opts)
def late_groups(room, lis_room, group, use_occ):
    """Per source: the late send it joins (0: the listener's room, or the room is unknown; 1 + r: room r) and
    whether its send falls with the direct path's transmission (its room is unknown)."""
    for i in range(len(room)):
        r = room[i]
        group[i] = r + 1 if (r >= 0 and r != lis_room) else 0
        use_occ[i] = r < 0


@njit(**_opts)
def groups_sending(group, send, seen):
    """How many distinct groups have a source with a non-zero send (seen (G,) bool scratch)."""
    seen[:] = False
    c = 0
    for i in range(len(group)):
        if send[i] > 0 and not seen[group[i]]:
            seen[group[i]] = True
            c += 1
    return c


@njit(**_opts)
def live_rows(x, prev, live):
    """live[g] = row g of x or of prev (the previous block) has a non-zero sample; returns how many are live."""
    c = 0
    for g in range(x.shape[0]):
        on = False
        for t in range(x.shape[1]):
            if x[g, t] != 0.0 or prev[g, t] != 0.0:
                on = True
                break
        live[g] = on
        c += on
    return c


@njit(**_fast)
def fdl_fill(X, curves, live, shaped, out):
    """One frequency-domain delay-line row: out[f] = sum over live groups g of X[g, f] (times curves[g, f] when
    shaped: the group's per-band coupling over the FFT bins)."""
    out[:] = 0
    for g in range(X.shape[0]):
        if not live[g]:
            continue
        if shaped:
            for f in range(X.shape[1]):
                out[f] += X[g, f] * curves[g, f]
        else:
            for f in range(X.shape[1]):
                out[f] += X[g, f]


@njit(**_opts)
def portal_curve(ratio, beta, bins, out):
    """The directional share's per-ear gains over FFT bins for a tail of which ``beta`` arrives from one direction:
    out[e, f] = sqrt(beta) sum_b bins[b, f] ratio[e, b] (ratio (2, B): that direction's per-band ear gains over the
    diffuse field's, normalised so that the two ears' mean power is 1; bins (B, F) the bands' interpolation
    weights). With the ears' own tails at sqrt(1 - beta), each ear's power per band is beta ratio^2 + 1 - beta, and
    the two ears' mean stays 1 in every band: a direction, no change of level."""
    E, F = out.shape
    nb = ratio.shape[1]
    a = np.sqrt(beta)
    for e in range(E):
        for f in range(F):
            g = 0.0
            for b in range(nb):
                g += bins[b, f] * ratio[e, b]
            out[e, f] = a * g


@njit(**_opts)
def delayed_add(hist, d0, d1, out):
    """out[e, t] += (1 - r) hist[e, D + t - d0[e]] + r hist[e, D + t - d1[e]], r = (t + 1) / B, D = hist's length
    - B: this block (hist's last B samples) delayed per ear, the delay ramped from d0 to d1 over the block."""
    E, B = out.shape
    D = hist.shape[1] - B
    for e in range(E):
        a, b = D - d0[e], D - d1[e]
        for t in range(B):
            r = (t + 1) / B
            out[e, t] += (1.0 - r) * hist[e, a + t] + r * hist[e, b + t]


@njit(**_fast)
def fdl_mac_add(fdl, H, off, p0, p1, out):
    """:func:`fdl_mac` over the delay line's rows p0..p1 - 1 only, added into ``out`` (not overwritten): a long
    partition's multiply-accumulate spread over the blocks of a period (``reverb.LongPartitions``)."""
    F = fdl.shape[1]
    E = out.shape[0]
    for p in range(p0, p1):
        for e in range(E):
            for f in range(F):
                out[e, f] += fdl[p, f] * H[off + p, e, f]


@njit(**_opts)
def long_close(frame, col, live_last, live_col, live, order):
    """A period of the long partitions ends: frame (G, 2L) becomes [last period | this period] (``col`` (G, L))
    for every group with sound in either (``live`` (G,): set here; a group silent in the last period gets zeros
    for it, since its frame may hold older samples), and this period's flags become the last's
    (``live_last`` = ``live_col``; ``live_col`` cleared). A group silent in both is left as it is (``live``
    False: nothing reads it). The live groups' indices go to the front of ``order``; returns how many there are."""
    G, L = col.shape
    c = 0
    for g in range(G):
        on = live_last[g] or live_col[g]
        live[g] = on
        if on:
            order[c] = g
            c += 1
            if live_last[g]:
                for t in range(L):
                    frame[g, t] = frame[g, L + t]
            else:
                for t in range(L):
                    frame[g, t] = 0.0
            for t in range(L):
                frame[g, L + t] = col[g, t]
        live_last[g] = live_col[g]
        live_col[g] = False
    return c


@njit(**_opts)
def pick_slots(w0, w1, slot_of):
    """The tails a period of long partitions computes: slot_of[s] = the tail with the s-th largest max(w0, w1)
    above 1e-4 (-1 past the last such tail)."""
    S = len(slot_of)
    for s in range(S):
        slot_of[s] = -1
        best = 1e-4
        for k in range(len(w0)):
            v = max(w0[k], w1[k])
            if v <= best:
                continue
            taken = False
            for r in range(s):
                if slot_of[r] == k:
                    taken = True
            if not taken:
                best = v
                slot_of[s] = k


@njit(**_opts)
def long_play(y, play, start, ready, w0, w1, lv0, lv1, scale, out):
    """A period's long partitions played out: out[e, t] += scale (w0[k] + (w1[k] - w0[k]) r) (lv0 + (lv1 - lv0) r)
    y[play, s, e, start + t] for every slot s whose tail k = ready[s] is mixed in (w0[k] or w1[k] above 1e-4),
    r = (t + 1) / B: :func:`mix_ramped` over the slots in one call. y (2, S, E, 2 L)."""
    E, B = out.shape
    for s in range(len(ready)):
        k = ready[s]
        if k < 0 or (w0[k] <= 1e-4 and w1[k] <= 1e-4):
            continue
        a, b = w0[k], w1[k]
        for t in range(B):
            r = (t + 1) / B
            g = scale * (a + (b - a) * r) * (lv0 + (lv1 - lv0) * r)
            for e in range(E):
                out[e, t] += g * y[play, s, e, start + t]


@njit(**_opts)
def long_take(x, col, start, live, live_col):
    """A block of the groups' sends into the period's columns: col[:, start:start + B] = x, live_col |= live."""
    G, B = x.shape
    for g in range(G):
        for t in range(B):
            col[g, start + t] = x[g, t]
        live_col[g] = live_col[g] or live[g]


@njit(**_opts)
def tail_blend(rt, mine, shut, weights, rt_now_mid, single, m0, m1, out, e):
    """A room's tails for the late re-mix: amplitude weights ``out`` (T,) over the tails ``rt`` (T, 9) (each probe's
    baked one, rows ``mine``, and its doors-shut one, rows ``shut[mine]``) for energies ``weights`` (P,) over the
    probes, blended between doors open and shut so that the mid-band (bands m0 to m1 - 1) RT is ``rt_now_mid``;
    ``e`` (9,) the blend's energy per band re the tails' normalisation (each tail carries rt_b / rt_mid of a flat one).
    ``mine`` empty: the probe of most energy instead. ``single``: the room's probe of most energy only, doors open
    or shut, whichever decays nearer (a neighbour's tail costs one convolution). Returns the doors-shut share."""
    only, best = -1, -1.0  # the one probe taken (empty room or single), else -1: all of mine
    if len(mine) == 0:
        for i in range(len(weights)):
            if weights[i] > best:
                only, best = i, weights[i]
    elif single:
        for i in mine:
            if weights[i] > best:
                only, best = i, weights[i]
    n = len(mine) if only < 0 else 1
    tot = 0.0
    for j in range(n):
        tot += weights[mine[j] if only < 0 else only]
    o_mid, s_mid = 0.0, 0.0
    for j in range(n):
        i = mine[j] if only < 0 else only
        p = weights[i] / tot if tot > 0 else 1.0 / n
        for b in range(m0, m1):
            o_mid += p * rt[i, b] / (m1 - m0)
            s_mid += p * rt[shut[i], b] / (m1 - m0)
    span = s_mid - o_mid  # a room without openings: no shut-door tail of its own
    beta = min(max((rt_now_mid - o_mid) / span, 0.0), 1.0) if span > 0.01 * o_mid else 0.0
    if single:
        beta = 1.0 if beta > 0.5 else 0.0
    out[:] = 0.0
    e[:] = 0.0
    for j in range(n):
        i = mine[j] if only < 0 else only
        p = weights[i] / tot if tot > 0 else 1.0 / n
        out[i] = math.sqrt(p * (1 - beta))
        out[shut[i]] += math.sqrt(p * beta)
        for b in range(len(e)):
            e[b] += p * ((1 - beta) * rt[i, b] / o_mid + beta * rt[shut[i], b] / s_mid)
    return beta
