"""The late reverb's compiled kernels (sonicverse_core/acoustics/late_kernels.py) against NumPy twins written from
their docstrings: the FDN, the sends to the reverb and their build-up, the partitioned convolution's steps, the
doorway's per-ear curve and delay (the glue kernels' twins are in test_kernels.py::test_block_glue_kernels, and
test_kernels.py::test_every_kernel_has_a_twin checks every kernel of both modules has one)."""
import numpy as np
import pytest

from sonicverse_core.acoustics import late_kernels as LK

FS = 48000.0
RNG = np.random.default_rng(11)


def test_fdn_process_is_a_householder_network():
    N, B = 4, 200
    delays = np.array([7, 11, 13, 17])
    size = 18
    b0, p = RNG.uniform(0.5, 0.9, N), RNG.uniform(-0.5, 0.5, N)
    cl, cr = RNG.choice([-1, 1], N) / 2.0, RNG.choice([-1, 1], N) / 2.0
    x = RNG.normal(size=B)
    buf, z = np.zeros((N, size)), np.zeros(N)
    out = np.empty((2, B))
    pos = LK.fdn_process(x, out, buf.copy(), 0, delays, b0, p, z.copy(), cl, cr, 0.7, np.empty(N))
    # twin: explicit matrix form, A = I - 2/N 1 1^T
    A = np.eye(N) - 2.0 / N
    rbuf, rz, ref = np.zeros((N, size)), np.zeros(N), np.zeros((2, B))
    for t in range(B):
        v = rbuf[np.arange(N), (t - delays) % size]
        ref[:, t] = [cl @ v * 0.7, cr @ v * 0.7]
        rz = b0 * v + p * rz
        rbuf[:, t % size] = A @ rz + x[t] / np.sqrt(N)
    np.testing.assert_allclose(out, ref, rtol=1e-10, atol=1e-12)
    assert pos == B % size


def test_late_send():
    n, B, H = 3, 32, 4096
    ring = RNG.normal(size=(n, H)).astype(np.float32)
    dist = np.array([1.0, 4.0, 9.0])
    occ = RNG.uniform(0, 1, (n, 9))
    p_send = np.array([0.2, 0.0, 0.7])
    D = np.round((dist / 343.0 + 0.012) * FS).astype(np.int64)
    p_delay = D + np.array([0, 5, 40])  # the third source moved (a teleport): its delay crossfades
    fresh = np.array([False, True, False])
    use_occ = np.array([True, True, False])  # the third source's room is known: no transmission factor
    group = np.array([0, 1, 1])
    rt = np.array([0.6, 1.4])  # each group's decay: the source's room's
    # the coupled modes heard apart, per group: the slowest, a neighbour's (its own, faster decay), an idle one
    rt_modes = np.array([[2.0, 2.5], [1.1, 1.6], [0.0, 0.0]])
    p_modes = np.array([[0.3, 0.2, 0.4], [0.0, 0.1, 0.0], [0.1, 0.3, 0.2]])
    # the first source's read across the ring's wrap, the third source's old read (it crossfades) across it, the
    # block read wholly behind the ring's start (it wraps)
    for w0 in (int(D[0]) - 10, int(D[2]) + 20, 40):
        out = np.empty((2, B), np.float32)
        pd = p_delay.copy()
        out_modes = np.empty((3, 2, B), np.float32)
        pm = p_modes.copy()
        LK.late_send(ring, w0, dist, occ, use_occ, group, rt, p_send.copy(), pd, fresh, out, FS, 343.0, 0.012,
                     rt_modes, pm, out_modes, np.empty((2, 3)), np.empty(B, np.float32))
        D0 = np.where(fresh, D, p_delay)
        r = (np.arange(B) + 1) / B
        rows = np.arange(n)[:, None]
        new_ = ring[rows, (w0 + np.arange(B)[None] - D[:, None]) % H]  # delayed: wraps the ring
        old_ = ring[rows, (w0 + np.arange(B)[None] - D0[:, None]) % H]
        src = np.where((D0 == D)[:, None], new_, old_ * (1 - r) + new_ * r)
        cases = [(out, rt[group], p_send)] + [(out_modes[k], rt_modes[k][group], p_modes[:, k]) for k in range(3)]
        for k, (sends, T, prev) in enumerate(cases):
            T = np.maximum(T, 0.05)
            s = 10 ** (-0.174 * dist / T / 20 - 3 * 0.012 / T) * np.where(use_occ, np.sqrt(occ[:, 4:7].mean(1)), 1.0)
            if k == 3:  # the idle mode: its sends ramp to silence
                s = np.zeros(n)
            s0 = np.where(fresh, s, prev)
            ramp = s0[:, None] + (s - s0)[:, None] * r
            for g in (0, 1):
                np.testing.assert_allclose(sends[g], (src * ramp)[group == g].sum(0), rtol=1e-5, atol=1e-6)
            if k:
                np.testing.assert_allclose(pm[:, k - 1], s)
        assert np.array_equal(pd, D)
    # a mode's distance law is its own: 0.174 r (1 / T_k - 1 / T_slow) dB below the slowest mode's
    assert not np.allclose(out_modes[0], out_modes[1])
    # no mode sends: out_modes (0, G, B) is left alone, the sends are the same
    out2 = np.empty((2, B), np.float32)
    LK.late_send(ring, 40, dist, occ, use_occ, group, rt, p_send.copy(), p_delay.copy(), fresh, out2, FS, 343.0,
                 0.012, rt_modes[:0], p_modes[:, :0].copy(), np.empty((0, 2, B), np.float32), np.empty((2, 0)),
                 np.empty(B, np.float32))
    np.testing.assert_array_equal(out2, out)


def test_buildup_filter():
    """Twin over six blocks through a ring of L + B samples that is not a multiple of B (blocks and taps wrap
    mid-run); each group its own delays, the longest L."""
    G, B, L = 4, 32, 50
    delay = np.array([[0, 7, 20, 50], [0, 7, 20, 49], [1, 2, 3, 4], [5, 0, 50, 30]])
    gain = np.array([0.6, 0.5, 0.4, 0.3], np.float32)
    x = RNG.normal(size=(G, 6 * B)).astype(np.float32)
    hist = np.zeros((G, L + B), np.float32)
    out, pos, wrapped = [], 0, 0
    for b in range(6):
        s = x[:, b * B:(b + 1) * B].copy()
        wrapped += 0 < hist.shape[1] - pos < B  # this block wraps mid-run
        pos = LK.buildup_filter(s, hist, pos, delay, gain, 2, np.empty(B))
        out.append(s)
        assert pos == (b + 1) * B % (L + B)
        stream = np.c_[np.zeros((G, L), np.float32), x]  # the ring holds the last L + B samples, ending before pos
        np.testing.assert_array_equal(np.roll(hist, -pos, axis=1), stream[:, b * B:L + (b + 1) * B])
    out = np.concatenate(out, axis=1)
    want = x.astype(np.float64).copy()
    for g in (1, 3):  # groups 0 and 2 (the listener's room) pass untouched
        want[g] = sum(a * np.r_[np.zeros(d), x[g, :6 * B - d]] for a, d in zip(gain, delay[g]))
    np.testing.assert_allclose(out, want, atol=1e-5)
    assert wrapped >= 2


def test_fdl_mac():
    P, F = 7, 17
    fdl = (RNG.normal(size=(P, F)) + 1j * RNG.normal(size=(P, F))).astype(np.complex64)
    H = (RNG.normal(size=(2 * P, 2, F)) + 1j * RNG.normal(size=(2 * P, 2, F))).astype(np.complex64)
    out = np.empty((2, F), np.complex64)
    LK.fdl_mac(fdl, H, 3, out)
    np.testing.assert_allclose(out, np.einsum("pf,pef->ef", fdl, H[3:3 + P]), rtol=1e-4, atol=1e-4)


def test_tail_partitions_reach_fdl_mac_in_c_order_whatever_order_the_fft_returns(monkeypatch):
    """NumPy 2's FFT returns its output in its input's memory order; the tail's partitions are cut from a transposed
    view, so they came out channel-outermost and fdl_mac (the callback's heaviest loop) compiled for a strided
    array: 2.8 times slower, the whole block 1.6 times (measured with NumPy 2.3.5). Here an FFT that keeps its
    input's order, as NumPy 2's does: the partitions are still C-ordered, hold the same values, and fdl_mac takes
    them as a C array."""
    from sonicverse_core.acoustics import reverb

    rng = np.random.default_rng(3)
    t = rng.standard_normal((2, 5 * 64))
    want = reverb._spectra(t, 5, 64)
    real = np.fft.rfft

    def keeps_order(x, n=None, axis=-1):  # the values of rfft, laid out in memory as its input is
        y = real(x, n, axis=axis)
        perm = list(np.argsort(np.asarray(x).strides)[::-1])  # axes from the slowest in memory to the fastest
        return np.ascontiguousarray(y.transpose(perm)).transpose(np.argsort(perm))

    monkeypatch.setattr(np.fft, "rfft", keeps_order)
    H = reverb._spectra(t, 5, 64)
    assert H.flags.c_contiguous and H.dtype == np.complex64 and not H.flags.writeable
    np.testing.assert_array_equal(H, want)
    out = np.zeros((2, 65), np.complex64)
    LK.fdl_mac(np.ones((5, 65), np.complex64), H, 2, out)
    assert all(sig[1].layout == "C" for sig in LK.fdl_mac.signatures), LK.fdl_mac.signatures


def test_portal_curve():
    """The directional share's gains: sqrt(beta) times the direction's level over the bins; with the diffuse share
    at sqrt(1 - beta), each ear's power per band is beta ratio^2 + 1 - beta (the two ears' mean: 1)."""
    ratio = np.abs(RNG.normal(size=(2, 9))) + 0.1
    ratio /= np.sqrt(np.mean(ratio ** 2, axis=0, keepdims=True))
    bins = np.abs(RNG.normal(size=(9, 33)))
    bins /= bins.sum(0, keepdims=True)
    out = np.empty((2, 33), np.complex64)  # PortalEars.gains: real values in the spectra's type
    eye = np.eye(9, 33)  # bins that are the bands themselves
    for beta in (0.0, 0.3, 1.0):
        LK.portal_curve(ratio, beta, bins, out)
        np.testing.assert_allclose(out.real, np.sqrt(beta) * ratio @ bins, rtol=1e-5, atol=1e-7)
        assert np.all(out.imag == 0)
        band = np.empty((2, 33), np.complex64)
        LK.portal_curve(ratio, beta, eye, band)
        power = band[:, :9].real ** 2 + (1 - beta)
        np.testing.assert_allclose(power, beta * ratio ** 2 + 1 - beta, rtol=1e-5)
        np.testing.assert_allclose(power.mean(0), 1.0, rtol=1e-5)


def test_delayed_add():
    """Twin: each ear's block delayed by its own whole samples, the delay ramped linearly from d0 to d1."""
    B, D = 16, 8
    hist = RNG.normal(size=(2, D + B))
    d0, d1 = np.array([0, 5]), np.array([3, 5])
    out = np.ones((2, B))
    LK.delayed_add(hist, d0, d1, out)
    r = (np.arange(B) + 1) / B
    for e in range(2):
        want = 1 + (1 - r) * hist[e, D - d0[e]:D - d0[e] + B] + r * hist[e, D - d1[e]:D - d1[e] + B]
        np.testing.assert_allclose(out[e], want, rtol=1e-12)
    np.testing.assert_allclose(out[1], 1 + hist[1, D - 5:D - 5 + B])  # a constant delay: the block delayed


def _blend_twin(rt, mine, shut_of, weights, rt_now_mid, single):
    """The late re-mix's blend as NumPy wrote it before the kernel (session 58's LateReverb._modal_mix)."""
    if len(mine) == 0:
        mine = np.array([int(np.argmax(weights))])
    if single:
        mine = mine[[int(np.argmax(weights[mine]))]]
    p = weights[mine] if weights[mine].sum() > 0 else np.ones(len(mine))
    p = p / p.sum()
    shut = shut_of[mine]
    o, s_ = rt[mine].T @ p, rt[shut].T @ p
    o_mid, s_mid = o[4:7].mean(), s_[4:7].mean()
    span = s_mid - o_mid
    beta = float(np.clip((rt_now_mid - o_mid) / span, 0.0, 1.0)) if span > 0.01 * o_mid else 0.0
    if single:
        beta = float(beta > 0.5)
    out = np.zeros(len(rt))
    out[mine] = np.sqrt(p * (1 - beta))
    out[shut] += np.sqrt(p * beta)
    return out, (1 - beta) * o / o_mid + beta * s_ / s_mid, beta


def test_tail_blend():
    """Twin: the tails' weights and energies of the late re-mix, for rooms with and without a doors-shut tail, a room
    without probes (the probe of most energy instead), one tail only (a neighbour's), weights all zero, and a
    target decay below, between and above the room's open and shut ones."""
    P = 7
    room = np.array([0, 0, 0, 1, 1, 2, -1])
    shut = np.arange(P)
    shut[:3], shut[3:5] = [7, 8, 9], [10, 11]  # room 2 has no openings: its probe is its own shut tail
    rt = np.abs(RNG.normal(0.5, 0.1, size=(P + 5, 9)))
    rt[P:] += 0.4  # doors shut: a slower decay
    out, e = np.empty(P + 5), np.empty(9)
    cases = 0
    for r_ in (0, 1, 2, 3):
        mine = np.flatnonzero(room == r_)
        for weights in (np.abs(RNG.normal(size=P)), np.zeros(P), np.r_[np.zeros(5), 1.0, 2.0]):
            for single in (False, True):
                for target in (0.1, 0.7, 2.0):
                    want_out, want_e, want_beta = _blend_twin(rt, mine, shut, weights, target, single)
                    beta = LK.tail_blend(rt, mine, shut, weights, target, single, 4, 7, out, e)
                    np.testing.assert_allclose(out, want_out, rtol=1e-12, atol=1e-14)
                    np.testing.assert_allclose(e, want_e, rtol=1e-12)
                    assert beta == pytest.approx(want_beta, abs=1e-12)
                    cases += 0 < want_beta < 1
    assert cases > 0  # some blends fall between doors open and shut
