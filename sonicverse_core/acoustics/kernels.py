"""Compiled per-sample kernels of the renderer (numba, cached on disk, GIL released).

NumPy would do each of these with several full-size temporaries per block; compiled loops touch every sample once
and release the GIL, so the audio thread and the frame loop can run side by side. Every kernel has a NumPy twin in
the tests that it must match (tests/test_kernels.py, gather's in tests/test_engine.py; a kernel without one fails
``test_every_kernel_has_a_twin``). The late reverb's kernels are in ``late_kernels.py``.
"""
from __future__ import annotations

import numpy as np
from numba import njit

_opts = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")
# reassociation (vectorised sums) without assuming finite values
_fast = dict(_opts, fastmath={"reassoc", "contract", "nsz", "arcp"})


@njit(**_opts)
def read_sources(bank, off, length, cursor, loop, gain, ring, w0, B):
    """Copy each source's next B samples (looping or one-shot, scaled by its gain) into ring[:, w0:w0+B]; a loop
    in runs between its wraps (:func:`_wrap_copy`)."""
    n = len(off)
    for i in range(n):
        L = length[i]
        c = cursor[i]
        g = np.float32(gain[i])
        dst = ring[i, w0:w0 + B]
        if L <= 0:
            for t in range(B):
                dst[t] = 0.0
        elif loop[i]:
            _wrap_copy(bank[off[i]:off[i] + L], c, g, dst)
        else:
            src = bank[off[i]:off[i] + L]
            m = min(B, max(L - c, 0))
            for k in range(m):
                dst[k] = src[c + k] * g
            for k in range(m, B):
                dst[k] = 0.0
        cursor[i] = c + B


@njit(**_opts)
def _wrap_copy(src, s, g, dst):
    """dst[t] = src[(s + t) mod len(src)] g (g float32): a ring or a loop read in runs between its wraps (a modulo
    per sample cost several times the copy)."""
    B, H = len(dst), len(src)
    j = s % H
    t = 0
    while t < B:
        m = min(B - t, H - j)
        x = src[j:j + m]
        y = dst[t:t + m]
        for k in range(m):
            y[k] = x[k] * g
        t += m
        j = 0


@njit(**_opts)
def gather(ring, base, d_old, d_new, fs, g_old, g_new, out, col):
    """Fractional-delay taps with linear interpolation: out[i, e, col + t] = ring[i, base + t - d(t) fs] * g(t),
    where delay d and gain g ramp linearly from *_old to *_new across the block (t = 1..B, B = L - col). ring
    (n, H); d_* (n, E); g_* (n, E) or (n, 1); out (n, E, L) float32, C-contiguous (a block's taps written into the
    end of a longer row, e.g. an overlap-save input, keep their rows contiguous: the common case's loop is
    vectorised only then)."""
    n, E, L = out.shape
    B = L - col
    for i in range(n):
        for e in range(E):
            d0 = d_old[i, e] * fs
            dd = (d_new[i, e] * fs - d0) / B
            ge = e if g_old.shape[1] > 1 else 0  # gains (n, 1) are shared by all taps of a source
            g0 = g_old[i, ge]
            dg = (g_new[i, ge] - g0) / B
            if g0 == 0.0 and dg == 0.0:
                for t in range(B):
                    out[i, e, col + t] = 0.0
                continue
            _tap(ring[i], base, d0, dd, g0, dg, out[i, e, col:])


@njit(**_opts)
def _tap(row, base, d0, dd, g0, dg, out):
    """One fractional-delay tap of a ring row into out (B,), delay d0 + dd (t + 1) samples, gain g0 + dg (t + 1).
    A delay that moves faster than half a sample per sample (Doppler factor 1.5: a teleport, not motion) is not
    swept but crossfaded from the old to the new delay."""
    B = len(out)
    H = len(row)
    if abs(dd) > 0.5:  # a jump (teleport): crossfade a tap at the old delay into one at the new delay
        d1 = d0 + dd * B
        for t in range(B):
            r = (t + 1) / B
            v = 0.0
            for dk, wk in ((d0, 1.0 - r), (d1, r)):
                pos = base + t - dk
                j = int(np.floor(pos))
                fr = pos - j
                j %= H
                j1 = j + 1 if j + 1 < H else 0
                v += (row[j] + (row[j1] - row[j]) * fr) * wk
            out[t] = v * (g0 + dg * (t + 1))
        return
    start = (base - d0 - dd) % H  # read position of t = 0, in [0, H)
    step = 1.0 - dd
    end = start + step * (B - 1)
    if abs(dd) * B <= 8.0 and end < H - 3:  # the common case: slow motion, no wrap inside the block
        _tap_runs(row, start, dd, g0, dg, out)
        return
    if step >= 0.0 and end < H - 2 and step < 1e6:  # faster motion, no wrap inside the block: 32.32 fixed point
        p = np.int64(start * 4294967296.0)
        inc = np.int64(step * 4294967296.0)
        g = g0 + dg
        for t in range(B):
            j = p >> 32
            fr = np.float32((p & 0xFFFFFFFF) * 2.3283064365386963e-10)
            a = row[j]
            out[t] = (a + (row[j + 1] - a) * fr) * np.float32(g)
            p += inc
            g += dg
        return
    for t in range(B):
        pos = start + step * t
        j = int(np.floor(pos))
        fr = pos - j
        j %= H
        j1 = j + 1
        if j1 == H:
            j1 = 0
        a = row[j]
        out[t] = (a + (row[j1] - a) * fr) * (g0 + dg * (t + 1))


@njit(**_opts)
def _tap_runs(row, start, dd, g0, dg, out):
    """_tap's common case: the delay moves by at most 8 samples across the block and the reads do not wrap. The
    read position start + (1 - dd) t is split into runs of samples whose integer part is j0 + e + t for one e (a
    run ends where the delay has moved by a whole sample, |dd| B + 1 runs at most), so each run reads the row
    contiguously and its loop is vectorised (a per-sample index would make it a gather)."""
    B = len(out)
    j0 = int(start)
    f0 = start - j0  # the fraction at t = 0, in [0, 1)
    ta = 0
    while ta < B:
        e = np.floor(f0 - dd * ta)  # this run's offset: floor(position) = j0 + e + t
        if dd > 0.0:  # the fraction falls: the run lasts while f0 - dd t >= e
            tb = ta + 1 + int(min((f0 - dd * ta - e) / dd, float(B)))
        elif dd < 0.0:  # it rises: while f0 - dd t < e + 1
            tb = ta + 1 + int(min((e + 1.0 - f0 + dd * ta) / -dd, float(B)))
        else:
            tb = B
        tb = min(tb, B)
        while tb > ta + 1 and np.floor(f0 - dd * (tb - 1)) != e:  # rounding: the same expression decides
            tb -= 1
        while tb < B and np.floor(f0 - dd * tb) == e:
            tb += 1
        o = j0 + int(e) + ta
        x = row[o:o + tb - ta + 1]
        y = out[ta:tb]
        fa = f0 - e - dd * ta
        ga = g0 + dg * (ta + 1)
        for k in range(tb - ta):
            a = x[k]
            y[k] = (a + (x[k + 1] - a) * np.float32(fa - dd * k)) * np.float32(ga + dg * k)
        ta = tb


@njit(**_fast)
def encode_taps(ring, base, d_old, d_new, fs, g_old, g_new, Y_old, Y_new, ramp, amb, tmp):
    """Image-source taps encoded into ambisonics: amb[c, t] += tap_ik(t) (Y_old[i, k, c] + (Y_new - Y_old) ramp[t])
    for source i and image k; taps whose gain stays 0 are skipped. amb (C, B) is overwritten; tmp (B,) float32
    scratch."""
    n, K = d_new.shape
    C, B = amb.shape
    amb[:] = 0.0
    for i in range(n):
        for k in range(K):
            g0 = g_old[i, k]
            g1 = g_new[i, k]
            if g0 == 0.0 and g1 == 0.0:
                continue
            d0 = d_old[i, k] * fs
            _tap(ring[i], base, d0, (d_new[i, k] * fs - d0) / B, g0, (g1 - g0) / B, tmp)
            for c in range(C):
                yo = np.float32(Y_old[i, k, c])
                dy = np.float32(Y_new[i, k, c]) - yo
                for t in range(B):
                    amb[c, t] += tmp[t] * (yo + dy * ramp[t])


@njit(**_opts)
def barycentric(dirs, grid, step, inv, tris, idx, w):
    """HRTF triangle and barycentric weights of unit vectors (m, 3): the grid cell's triangle first, then the
    whole hull (the triangle whose smallest weight is largest). Writes vertex indices idx (m, 3) int64 and weights
    w (m, 3)."""
    m = dirs.shape[0]
    na, ne = grid.shape[0], grid.shape[1]
    for i in range(m):
        x, y, z = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        r = np.sqrt(x * x + y * y + z * z)
        if r < 1e-12:
            x, y, z, r = 1.0, 0.0, 0.0, 1.0
        x, y, z = x / r, y / r, z / r
        ia = int((np.degrees(np.arctan2(y, x)) + 180.0) / step)
        ie = int((np.degrees(np.arcsin(min(1.0, max(-1.0, z)))) + 90.0) / step)
        ia = min(max(ia, 0), na - 1)
        ie = min(max(ie, 0), ne - 1)
        nc = grid.shape[2]
        best, bmin = grid[ia, ie, 0], -1e30
        for k in range(-nc, len(tris)):  # the cell's candidates first, then every triangle
            tt = grid[ia, ie, k + nc] if k < 0 else k
            w0 = inv[tt, 0, 0] * x + inv[tt, 0, 1] * y + inv[tt, 0, 2] * z
            w1 = inv[tt, 1, 0] * x + inv[tt, 1, 1] * y + inv[tt, 1, 2] * z
            w2 = inv[tt, 2, 0] * x + inv[tt, 2, 1] * y + inv[tt, 2, 2] * z
            mn = min(w0, min(w1, w2))
            if mn > bmin:
                bmin, best = mn, tt
            if mn >= -1e-9:
                break
        tt = best
        w0 = max(0.0, inv[tt, 0, 0] * x + inv[tt, 0, 1] * y + inv[tt, 0, 2] * z)
        w1 = max(0.0, inv[tt, 1, 0] * x + inv[tt, 1, 1] * y + inv[tt, 1, 2] * z)
        w2 = max(0.0, inv[tt, 2, 0] * x + inv[tt, 2, 1] * y + inv[tt, 2, 2] * z)
        s = max(w0 + w1 + w2, 1e-12)
        idx[i, 0], idx[i, 1], idx[i, 2] = tris[tt, 0], tris[tt, 1], tris[tt, 2]
        w[i, 0], w[i, 1], w[i, 2] = w0 / s, w1 / s, w2 / s


@njit(**_opts)
def nearest_direction(dirs, measured, idx, w):
    """The measured direction (rows of measured (n, 3), unit) nearest each of dirs (m, 3): the largest dot
    product; idx[i] = (j, j, j), w[i] = (1, 0, 0)."""
    for i in range(dirs.shape[0]):
        best, bj = -np.inf, 0
        for j in range(measured.shape[0]):
            v = dirs[i, 0] * measured[j, 0] + dirs[i, 1] * measured[j, 1] + dirs[i, 2] * measured[j, 2]
            if v > best:
                best, bj = v, j
        idx[i, 0], idx[i, 1], idx[i, 2] = bj, bj, bj
        w[i, 0], w[i, 1], w[i, 2] = 1.0, 0.0, 0.0


@njit(**_fast)
def mix_spectra(H, idx, w, curve, spread, diffuse, out):
    """out[i, e, f] = (sum_k w[i, k] H[idx[i, k], e, f] (1 - s_i) + s_i diffuse[e, f]) * curve[i, f]."""
    n, E, F = out.shape
    for i in range(n):
        a, b, c = idx[i, 0], idx[i, 1], idx[i, 2]
        wa, wb, wc = np.float32(w[i, 0]), np.float32(w[i, 1]), np.float32(w[i, 2])
        s = np.float32(spread[i])
        for e in range(E):
            for f in range(F):
                h = wa * H[a, e, f] + wb * H[b, e, f] + wc * H[c, e, f]
                if s > 0:
                    h = h * (1 - s) + diffuse[e, f] * s
                out[i, e, f] = h * curve[i, f]


@njit(**_fast)
def accumulate(X, spec, p_spec, acc_new, acc_old):
    """acc_new = sum_i X[i] spec[i]; acc_old = sum_i X[i] p_spec[i]. Returns True when some filter changed."""
    n, E, F = X.shape
    acc_new[:] = 0
    acc_old[:] = 0
    changed = False
    for i in range(n):
        for e in range(E):
            if not changed:
                for f in range(F):
                    if p_spec[i, e, f] != spec[i, e, f]:
                        changed = True
                        break
            for f in range(F):
                acc_new[e, f] += X[i, e, f] * spec[i, e, f]
            for f in range(F):
                acc_old[e, f] += X[i, e, f] * p_spec[i, e, f]
    return changed


@njit(**_opts)
def distance_gain_1(d, mode, d0, D, near_k):
    """Rolloff gain (Resonance Audio's curves: mode 0 log, 1 linear, 2 none; 0 beyond D) times the bounded
    near-field boost under 1 m."""
    if d > D:
        return 0.0
    if mode == 0:
        g = (1.0 / (max(d, d0) - d0 + 1.0) - 1.0 / (1.0 + D - d0)) / (1.0 - 1.0 / (1.0 + D - d0))
    elif mode == 1:
        g = min(1.0, max(0.0, (D - max(d, d0)) / (D - d0)))
    else:
        g = 1.0
    if d < 1.0:
        g *= 1.0 + (1.0 / max(d, 0.1) - 1.0) * near_k
    return g


@njit(**_opts)
def _image(s, lo, hi, q, m, lis):
    """One coordinate of an image source (relative to the listener): the source clamped into [lo, hi], mirrored
    q times (0/1) and shifted by m box lengths."""
    L = hi - lo
    x = min(max(s - lo, 0.0), L)
    return (1 - 2 * q) * x + 2 * m * L + lo - lis


@njit(**_opts)
def image_taps(src, lo, hi, q, m, amp, lis, R, mode, d0, D, near_k, occ, bulk, c_sound, delay, gain, Y):
    """Image sources of the box [lo, hi] for sources src (n, 3) as heard at lis: delay
    (n, K) s, gain (n, K) (distance law x wall reflections x occ (n,)), and 2nd-order N3D SH (n, K, 9) of the
    direction in the head frame (R: world -> head rotation); occ (n, 9): the per-band transmission, whose mid-band
    (500 Hz - 2 kHz) mean scales the images. Sources more than 0.5 m outside the box get no images (gain 0); those
    within that margin are clamped into it."""
    n, K = delay.shape
    for i in range(n):
        inside = True
        for a in range(3):
            if src[i, a] < lo[a] - 0.5 or src[i, a] > hi[a] + 0.5:
                inside = False
        for k in range(K):
            if not inside:  # image sources of this box do not exist for a source outside it
                gain[i, k] = 0.0
                delay[i, k] = 0.0
                for c in range(9):
                    Y[i, k, c] = 0.0
                continue
            v0, v1, v2 = _image(src[i, 0], lo[0], hi[0], q[k, 0], m[k, 0], lis[0]), \
                _image(src[i, 1], lo[1], hi[1], q[k, 1], m[k, 1], lis[1]), \
                _image(src[i, 2], lo[2], hi[2], q[k, 2], m[k, 2], lis[2])
            d = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            g = distance_gain_1(d, mode, d0, D, near_k) * amp[k] * (occ[i, 4] + occ[i, 5] + occ[i, 6]) / 3.0
            gain[i, k] = g if g >= 1e-4 else 0.0  # below -80 dB: left out
            delay[i, k] = min(d, D) / c_sound + bulk
            _sh9(R, v0, v1, v2, d, Y[i, k])


@njit(**_opts)
def _sh9(R, v0, v1, v2, d, y9):
    """The 2nd-order N3D spherical harmonics (y9, 9) of the world direction (v0, v1, v2) / d in the head frame (R:
    world -> head)."""
    s3, s15, s5h = np.sqrt(3.0), np.sqrt(15.0), np.sqrt(5.0) / 2
    inv = 1.0 / max(d, 1e-9)
    x = (R[0, 0] * v0 + R[0, 1] * v1 + R[0, 2] * v2) * inv
    y = (R[1, 0] * v0 + R[1, 1] * v1 + R[1, 2] * v2) * inv
    z = (R[2, 0] * v0 + R[2, 1] * v1 + R[2, 2] * v2) * inv
    y9[0] = 1.0
    y9[1] = s3 * y
    y9[2] = s3 * z
    y9[3] = s3 * x
    y9[4] = s15 * x * y
    y9[5] = s15 * y * z
    y9[6] = s5h * (3 * z * z - 1)
    y9[7] = s15 * x * z
    y9[8] = s15 / 2 * (x * x - y * y)


@njit(**_opts)
def limit(out, res, g, release):
    """Safety limiter, one pass: non-finite samples -> 0; when the block's peak exceeds 0.99 the gain falls to
    0.99 / peak within a quarter block (samples still above 1 are clipped), and recovers by ``release`` per
    block; magnitudes under 1e-30 become exact zeros (no denormals downstream). out (E, B) float64 -> res float32.
    Returns the gain at the block's end."""
    E, B = out.shape
    peak = 0.0
    for e in range(E):
        for t in range(B):
            v = out[e, t]
            if not np.isfinite(v):
                out[e, t] = 0.0
            elif abs(v) > peak:
                peak = abs(v)
    target = 0.99 / peak if peak > 0.99 else 1.0
    goal = min(target, g + release)
    q = max(1, B // 4)
    for e in range(E):
        for t in range(B):
            gg = g + (goal - g) * min(1.0, (t + 1) / q)
            v = out[e, t] * gg
            if v > 1.0:
                v = 1.0
            elif v < -1.0:
                v = -1.0
            elif abs(v) < 1e-30:
                v = 0.0
            res[e, t] = v
    return goal


@njit(**_opts)
def direct_geometry(pos, lis, R, fwd, alpha, sharp, occ, air, mode, d0, D, near_k, c_sound,
                    dirs, dist, gain, amp, delay):
    """Per source: unit direction in the head frame (R: world -> head), distance, gain (distance law x
    directivity |(1 - a) + a cos|^sharpness), per-band amplitude (air absorption x occlusion, float32) and
    propagation delay (s)."""
    n = pos.shape[0]
    for i in range(n):
        vx, vy, vz = pos[i, 0] - lis[0], pos[i, 1] - lis[1], pos[i, 2] - lis[2]
        d = np.sqrt(vx * vx + vy * vy + vz * vz)
        dist[i] = d
        if d > 1e-6:
            inv = 1.0 / d
            dirs[i, 0] = (R[0, 0] * vx + R[0, 1] * vy + R[0, 2] * vz) * inv
            dirs[i, 1] = (R[1, 0] * vx + R[1, 1] * vy + R[1, 2] * vz) * inv
            dirs[i, 2] = (R[2, 0] * vx + R[2, 1] * vy + R[2, 2] * vz) * inv
            cos_t = -(fwd[i, 0] * vx + fwd[i, 1] * vy + fwd[i, 2] * vz) * inv
        else:
            dirs[i, 0], dirs[i, 1], dirs[i, 2] = 1.0, 0.0, 0.0
            cos_t = 1.0
        g = distance_gain_1(d, mode, d0, D, near_k)
        if alpha[i] > 0:
            g *= abs((1 - alpha[i]) + alpha[i] * cos_t) ** sharp[i]
        gain[i] = g
        dm = min(d, D)
        for b in range(air.shape[0]):
            amp[i, b] = np.float32(np.exp(-0.5 * air[b] * dm) * occ[i, b])
        delay[i] = dm / c_sound


@njit(**_opts)
def segment_motion(pos, lis, seg, out):
    """How far (max-norm) each source->listener segment's ends moved since seg (n, 6) was cast (inf if never)."""
    for i in range(pos.shape[0]):
        m = 0.0
        for a in range(3):
            u, v = abs(pos[i, a] - seg[i, a]), abs(lis[a] - seg[i, 3 + a])
            if not (u == u and v == v):  # NaN: a segment never cast (max() would drop the NaN)
                m = np.inf
                break
            m = max(m, u, v)
        out[i] = m


@njit(**_fast)
def accumulate_sh(A, filters, acc):
    """acc[e, f] = sum_c A[c, f] filters[c, e, f] (ambisonic channels -> ears)."""
    C, E, F = filters.shape
    acc[:] = 0
    for c in range(C):
        for e in range(E):
            for f in range(F):
                acc[e, f] += A[c, f] * filters[c, e, f]


@njit(**_opts)
def distance_gains(d, mode, d0, D, near_k, out):
    """distance_gain_1 over an array."""
    for i in range(len(d)):
        out[i] = distance_gain_1(d[i], mode, d0, D, near_k)


# --- the per-block glue of the renderer: each replaces a NumPy expression that made temporaries ----------------------
@njit(**_opts)
def onset_delays(w, idx, onsets, delay0, spread, mean_onset, out):
    """out[i, e] = delay0[i] + o, o = sum_k w[i, k] onsets[idx[i, k], e] blended towards mean_onset[e] by spread[i]
    (the fully spread source's onset is the set's mean)."""
    for i in range(out.shape[0]):
        for e in range(out.shape[1]):
            o = w[i, 0] * onsets[idx[i, 0], e] + w[i, 1] * onsets[idx[i, 1], e] + w[i, 2] * onsets[idx[i, 2], e]
            out[i, e] = delay0[i] + o + (mean_onset[e] - o) * spread[i]


@njit(**_opts)
def smooth_toward(occ, target, k, fresh, mute):
    """occ += (1 - k) (target - occ), except occ = target where fresh and 0 where mute (rows: sources)."""
    for i in range(occ.shape[0]):
        for b in range(occ.shape[1]):
            if mute[i]:
                occ[i, b] = 0.0
            elif fresh[i]:
                occ[i, b] = target[i, b]
            else:
                occ[i, b] += (1.0 - k) * (target[i, b] - occ[i, b])


@njit(**_opts)
def shift_left(h, B):
    """h[:, :-B] = h[:, B:] (rows of an overlap-save history; h (m, N))."""
    m, N = h.shape
    for i in range(m):
        for t in range(N - B):
            h[i, t] = h[i, t + B]


@njit(**_opts)
def crossfade_into(both, ramp, scale, xfade, out):
    """out[e, t] += scale (y0 + (y1 - y0) ramp[t]) with y_j = both[j, e, N - B + t] (the last B samples of the old
    (j = 0) and new (j = 1) filters' outputs); without xfade out += scale y1."""
    E, B = out.shape
    off = both.shape[2] - B
    for e in range(E):
        for t in range(B):
            y1 = both[1, e, off + t]
            if xfade:
                y0 = both[0, e, off + t]
                out[e, t] += scale * (y0 + (y1 - y0) * ramp[t])
            else:
                out[e, t] += scale * y1


@njit(**_opts)
def add_tail(y, scale, out):
    """out[e, t] += scale y[e, N - B + t]: the last B samples of y (E, N)."""
    E, B = out.shape
    off = y.shape[1] - B
    for e in range(E):
        for t in range(B):
            out[e, t] += scale * y[e, off + t]


@njit(**_opts)
def pan_spectra(dirs, curve, mono, spec):
    """Without HRTFs: spec[i, 0] = sqrt((1 + y_i) / 2) curve[i], spec[i, 1] = sqrt((1 - y_i) / 2) curve[i] (y: the
    unit direction's lateral component, +y left), or sqrt(1/2) curve[i] in both channels when mono."""
    for i in range(dirs.shape[0]):
        if mono:
            gl = gr = np.sqrt(0.5)
        else:
            r = np.sqrt(dirs[i, 0] ** 2 + dirs[i, 1] ** 2 + dirs[i, 2] ** 2)
            y = dirs[i, 1] / r if r > 0 else 0.0
            gl, gr = np.sqrt(0.5 * (1 + y)), np.sqrt(0.5 * (1 - y))
        for f in range(curve.shape[1]):
            spec[i, 0, f] = np.float32(gl) * curve[i, f]
            spec[i, 1, f] = np.float32(gr) * curve[i, f]


@njit(**_opts)
def woodworth_delays(dirs, delay0, a_over_c, out):
    """Without HRTFs (stereo): per-ear delays out[i, e] = delay0[i] + (a/c)(pi/2 + 1)/2 -+ ITD_i/2 (left -, right +),
    ITD_i = (a/c)(theta_i + sin theta_i) (Woodworth), theta_i = asin(y_i) the lateral angle (+ left); the common
    offset keeps both ears at or after delay0 (a sound at 90 degrees reaches the far ear (a/c)(pi/2 + 1) later)."""
    half = 0.5 * a_over_c * (0.5 * np.pi + 1.0)
    for i in range(dirs.shape[0]):
        r = np.sqrt(dirs[i, 0] ** 2 + dirs[i, 1] ** 2 + dirs[i, 2] ** 2)
        y = min(max(dirs[i, 1] / r, -1.0), 1.0) if r > 0 else 0.0
        th = np.arcsin(y)
        itd = a_over_c * (th + np.sin(th))
        out[i, 0] = delay0[i] + half - 0.5 * itd
        out[i, 1] = delay0[i] + half + 0.5 * itd


@njit(**_opts)
def all_finite(x):
    """True when every element of x (any shape) is finite."""
    for v in x.flat:
        if not np.isfinite(v):
            return False
    return True


@njit(**_opts)
def head_rotation(yaw, pitch, R):
    """World -> head frame rotation (x forward, y left, z up): yaw about z, then pitch (degrees), into R (3, 3)."""
    c, s = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
    cp, sp = np.cos(np.radians(pitch)), np.sin(np.radians(pitch))
    R[0, 0], R[0, 1], R[0, 2] = cp * c, cp * s, sp
    R[1, 0], R[1, 1], R[1, 2] = -s, c, 0.0
    R[2, 0], R[2, 1], R[2, 2] = -sp * c, -sp * s, cp


@njit(**_opts)
def rows_moved(a, b, tol, mask):
    """mask[i] = max_j |a[i, j] - b[i, j]| > tol (NaN counts as moved); returns how many rows moved."""
    count = 0
    for i in range(a.shape[0]):
        moved = False
        for j in range(a.shape[1]):
            d = abs(a[i, j] - b[i, j])
            if not (d <= tol):
                moved = True
                break
        mask[i] = moved
        count += moved
    return count


@njit(**_opts)
def scale_into(x, g, out):
    """out[t] = x[t] g (a live source's pushed block into its ring row)."""
    for t in range(len(out)):
        out[t] = x[t] * g


@njit(**_opts)
def lerp(a, b, r, out):
    """out = a + (b - a) r (the pose interpolator's step)."""
    for j in range(len(out)):
        out[j] = a[j] + (b[j] - a[j]) * r


@njit(**_opts)
def farther(a, b, tol):
    """max_j |a[j] - b[j]| > tol, or a NaN (1-D vectors: has a point moved?)."""
    for j in range(len(a)):
        if not (abs(a[j] - b[j]) <= tol):
            return True
    return False


@njit(**_opts)
def count_over(x, tol):
    """How many elements of x (1-D) exceed tol."""
    c = 0
    for i in range(len(x)):
        if x[i] > tol:
            c += 1
    return c


@njit(**_opts)
def segments_meet_boxes(a, b, lo, hi, out):
    """out[i] = does segment a[i] -> b (a (n, 3), b (3,): the listener, shared) meet any box [lo[j], hi[j]] ((m, 3)
    each)? The slab test of ``occlusion.segment_meets_boxes`` (its NumPy twin), without its (n, m, 3) temporaries:
    the occlusion recast runs it over every part's box in the blocks that cast."""
    for i in range(a.shape[0]):
        hit = False
        for j in range(lo.shape[0]):
            tmin, tmax = -np.inf, np.inf
            for k in range(3):
                d = b[k] - a[i, k]
                if abs(d) < 1e-12:
                    d = 1e-12
                inv = 1.0 / d
                t0 = (lo[j, k] - a[i, k]) * inv
                t1 = (hi[j, k] - a[i, k]) * inv
                if t0 > t1:
                    t0, t1 = t1, t0
                tmin = max(tmin, t0)
                tmax = min(tmax, t1)
            if tmax >= max(tmin, 0.0) and tmin <= 1.0:
                hit = True
                break
        out[i] = hit


@njit(**_opts)
def _crossed_part(j, face, ci, s_part, s_mat, d_part, d_mat, offset):
    """The part (dynamic parts shifted by offset) and material of hit j of a walk (:meth:`SceneRayCaster.walk`:
    caster 0 the static mesh, 1 the dynamic one)."""
    f = face[j]
    if ci[j] == 0:
        return np.int64(s_part[f]), np.int64(s_mat[f])
    return np.int64(d_part[f]) + offset, np.int64(d_mat[f])


@njit(**_opts)
def occlusion_logs(ray, dist, face, ci, s_part, s_mat, d_part, d_mat, offset, bounds, starts, log_trans, logamp):
    """What the occlusion recast makes of a walk's hits (ray, dist, face, ci (k,), in any order): per segment r,
    the sum over the parts it crosses, each part once with its nearest crossing's material (ties: the earlier
    hit), of log_trans[material] (bands), into logamp (n, bands). A dynamic part q - offset whose bounds
    (:func:`occlusion.sounding_bounds`, (m, 2, 3)) hold the segment's start (starts (n, 3)) is the object the sound
    comes from and is left out (:func:`occlusion.own_object_crossings`)."""
    logamp[:] = 0.0
    k = len(ray)
    for j in range(k):
        r = ray[j]
        p, m = _crossed_part(j, face, ci, s_part, s_mat, d_part, d_mat, offset)
        q = p - offset
        if ci[j] != 0 and 0 <= q < bounds.shape[0]:
            own = True
            for c in range(3):
                if not (bounds[q, 0, c] <= starts[r, c] <= bounds[q, 1, c]):
                    own = False
            if own:
                continue
        first = True
        for jj in range(k):
            if jj == j or ray[jj] != r:
                continue
            p2, _ = _crossed_part(jj, face, ci, s_part, s_mat, d_part, d_mat, offset)
            if p2 == p and (dist[jj] < dist[j] or (dist[jj] == dist[j] and jj < j)):
                first = False
                break
        if first:
            for c in range(logamp.shape[1]):
                logamp[r, c] += log_trans[m, c]
