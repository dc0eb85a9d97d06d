"""Every compiled kernel of the renderer (sonicverse_core/acoustics/kernels.py) against a NumPy twin written from its
docstring: the loops must compute what the vectorised formula says (gather's twin is in test_engine.py, the late
reverb's kernels' in test_late_kernels.py)."""
import numpy as np
import pytest

from sonicverse_core.acoustics import early_kernels as EK
from sonicverse_core.acoustics import kernels as K
from sonicverse_core.acoustics import late_kernels as LK

FS = 48000.0
RNG = np.random.default_rng(11)


def _log_gain(d, d0, D):
    d = np.asarray(d, float)
    return (1 / (np.maximum(d, d0) - d0 + 1) - 1 / (1 + D - d0)) / (1 - 1 / (1 + D - d0))


def _distance_twin(d, mode, d0, D, near_k):
    d = np.asarray(d, float)
    if mode == 0:
        g = _log_gain(d, d0, D)
    elif mode == 1:
        g = np.clip((D - np.maximum(d, d0)) / (D - d0), 0, 1)
    else:
        g = np.ones_like(d)
    g = np.where(d < 1, g * (1 + (1 / np.maximum(d, 0.1) - 1) * near_k), g)
    return np.where(d > D, 0.0, g)


@pytest.mark.parametrize("mode", [0, 1, 2])
def test_distance_gains(mode):
    d = np.r_[0.0, 0.05, 0.3, 0.99, 1.0, 2.5, 10, 499, 501, RNG.uniform(0, 600, 50)]
    out = np.empty_like(d)
    K.distance_gains(d, mode, 1.0, 500.0, 1 / 3, out)
    np.testing.assert_allclose(out, _distance_twin(d, mode, 1.0, 500.0, 1 / 3), rtol=1e-12, atol=1e-15)
    assert K.distance_gain_1(3.0, mode, 1.0, 500.0, 0.0) == pytest.approx(_distance_twin(3.0, mode, 1.0, 500.0, 0))


def test_read_sources():
    n, B, H = 6, 64, 512
    bank = RNG.normal(size=1000).astype(np.float32)
    # looping: no wrap, one wrap, a loop shorter than the block (wraps 3 times), a cursor many loops on; one-shot:
    # ending inside the block, ended before it
    off, length = np.array([1, 200, 500, 950, 300, 10]), np.array([150, 90, 400, 17, 33, 40])
    cursor = np.array([0, 60, 380, 5, 1000 * 33 + 31, 70])
    loop = np.array([True, True, False, True, True, False])
    gain = np.array([0.5, 2.0, 1.0, 0.7, 1.3, 1.0])
    ring = np.full((n, H), 7.0, np.float32)
    K.read_sources(bank, off, length, cursor.copy(), loop, gain, ring, 100, B)
    for i in range(n):
        k = cursor[i] + np.arange(B)
        if loop[i]:
            ref = bank[off[i] + k % length[i]] * np.float32(gain[i])
        else:
            ref = np.where(k < length[i], bank[off[i] + np.minimum(k, length[i] - 1)], 0) * np.float32(gain[i])
        np.testing.assert_allclose(ring[i, 100:100 + B], ref, rtol=1e-6)
    assert np.all(ring[:, :100] == 7.0) and np.all(ring[:, 100 + B:] == 7.0)  # nothing outside the block is touched


def test_mix_spectra_and_accumulate():
    m, E, F, n = 10, 2, 33, 4
    H = (RNG.normal(size=(m, E, F)) + 1j * RNG.normal(size=(m, E, F))).astype(np.complex64)
    idx = RNG.integers(0, m, (n, 3))
    w = RNG.dirichlet(np.ones(3), n)
    curve = RNG.uniform(0, 1, (n, F)).astype(np.float32)
    spread = np.array([0.0, 0.3, 1.0, 0.0])
    diffuse = np.abs(H).mean(0).astype(np.complex64)
    out = np.empty((n, E, F), np.complex64)
    K.mix_spectra(H, idx, w, curve, spread, diffuse, out)
    ref = np.einsum("nk,nkef->nef", w, H[idx])
    ref = np.where(spread[:, None, None] > 0, ref * (1 - spread[:, None, None]) + diffuse * spread[:, None, None], ref)
    np.testing.assert_allclose(out, ref * curve[:, None, :], rtol=1e-4, atol=1e-5)

    X = (RNG.normal(size=(n, E, F)) + 1j * RNG.normal(size=(n, E, F))).astype(np.complex64)
    p_spec = out.copy()
    acc_new, acc_old = np.empty((E, F), np.complex64), np.empty((E, F), np.complex64)
    assert K.accumulate(X, out, p_spec, acc_new, acc_old) is False  # same filters: nothing changed
    p_spec[2, 1, 5] += 1
    assert K.accumulate(X, out, p_spec, acc_new, acc_old) is True
    np.testing.assert_allclose(acc_new, (X * out).sum(0), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(acc_old, (X * p_spec).sum(0), rtol=1e-4, atol=1e-4)


def test_accumulate_sh():
    C, E, F = 9, 2, 65
    A = (RNG.normal(size=(C, F)) + 1j * RNG.normal(size=(C, F))).astype(np.complex64)
    filt = (RNG.normal(size=(C, E, F)) + 1j * RNG.normal(size=(C, E, F))).astype(np.complex64)
    acc = np.empty((E, F), np.complex64)
    K.accumulate_sh(A, filt, acc)
    np.testing.assert_allclose(acc, np.einsum("cf,cef->ef", A, filt), rtol=1e-4, atol=1e-4)


def test_limit():
    out = np.array([[0.1, -0.5, np.nan, 3.0, 1e-35, -0.2], [0.2, np.inf, -4.0, 0.5, 0.3, 0.0]])
    res = np.empty(out.shape, np.float32)
    g = K.limit(out.copy(), res, 1.0, 0.05)
    clean = np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)
    peak = np.abs(clean).max()
    goal = min(0.99 / peak, 1.0 + 0.05)
    ramp = 1.0 + (goal - 1.0) * np.minimum(1.0, (np.arange(6) + 1) / max(1, 6 // 4))
    ref = np.clip(clean * ramp, -1, 1)
    ref[np.abs(ref) < 1e-30] = 0.0
    assert g == pytest.approx(goal)
    np.testing.assert_allclose(res, ref.astype(np.float32), rtol=1e-6)
    assert np.all(np.isfinite(res)) and np.abs(res).max() <= 1.0


def test_direct_geometry():
    n = 6
    pos = RNG.uniform(-5, 5, (n, 3))
    pos[0] = [1.0, 2.0, 1.5]  # at the listener
    lis = np.array([1.0, 2.0, 1.5])
    yaw = np.radians(30)
    R = np.array([[np.cos(yaw), np.sin(yaw), 0], [-np.sin(yaw), np.cos(yaw), 0], [0, 0, 1.0]])
    fwd = RNG.normal(size=(n, 3))
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    alpha, sharp = RNG.uniform(0, 1, n), RNG.uniform(1, 3, n)
    alpha[1] = 0.0
    occ = RNG.uniform(0, 1, (n, 9))
    air = np.array([.0006, .0006, .0007, .0008, .0010, .0015, .0026, .0060, .0207])
    dirs, dist, gain, amp, delay = np.empty((n, 3)), np.empty(n), np.empty(n), np.empty((n, 9), np.float32), \
        np.empty(n)
    K.direct_geometry(pos, lis, R, fwd, alpha, sharp, occ, air, 0, 1.0, 500.0, 1 / 3, 343.0, dirs, dist, gain, amp,
                      delay)
    v = pos - lis
    d = np.linalg.norm(v, axis=1)
    u = np.where(d[:, None] > 1e-6, (v @ R.T) / np.maximum(d, 1e-300)[:, None], [1.0, 0, 0])
    cos_t = np.where(d > 1e-6, -np.einsum("ij,ij->i", fwd, v) / np.maximum(d, 1e-300), 1.0)
    g = _distance_twin(d, 0, 1.0, 500.0, 1 / 3) * np.where(alpha > 0, np.abs(1 - alpha + alpha * cos_t) ** sharp, 1)
    np.testing.assert_allclose(dist, d, rtol=1e-12)
    np.testing.assert_allclose(dirs, u, atol=1e-12)
    np.testing.assert_allclose(gain, g, rtol=1e-12)
    np.testing.assert_allclose(amp, np.exp(-0.5 * air[None] * d[:, None]) * occ, rtol=1e-6)
    np.testing.assert_allclose(delay, d / 343.0, rtol=1e-12)


def test_segment_motion():
    pos, lis = RNG.normal(size=(4, 3)), RNG.normal(size=3)
    seg = np.c_[pos + RNG.normal(size=(4, 3)) * 0.1, np.tile(lis, (4, 1))]
    seg[3] = np.nan  # never cast
    out = np.empty(4)
    K.segment_motion(pos, lis, seg, out)
    ref = np.max(np.abs(np.c_[pos, np.tile(lis, (4, 1))] - seg), axis=1)
    ref[3] = np.inf
    np.testing.assert_allclose(out, ref)


def test_segments_meet_boxes():
    """The compiled slab test agrees with its NumPy twin (``occlusion.segment_meets_boxes``) on random segments and
    boxes, on segments along an axis (a zero direction component), on boxes the segment ends inside or stops short of,
    and answers what a hand check says."""
    from sonicverse_core.acoustics.occlusion import segment_meets_boxes

    a, lis = RNG.uniform(-3, 3, size=(400, 3)), RNG.uniform(-1, 1, size=3)
    a[:50, 1:] = lis[1:]  # along x through the listener's y and z
    c, h = RNG.uniform(-3, 3, size=(30, 3)), RNG.uniform(0.05, 0.6, size=(30, 3))
    lo, hi = c - h, c + h
    out = np.empty(len(a), bool)
    K.segments_meet_boxes(a, lis, lo, hi, out)
    ref = segment_meets_boxes(a, np.broadcast_to(lis, a.shape), lo, hi)
    np.testing.assert_array_equal(out, ref)
    assert 0.1 < out.mean() < 0.9  # both answers occur
    box = np.array([[1.0, -0.5, -0.5]]), np.array([[2.0, 0.5, 0.5]])
    ends = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.5, 0.0, 0.0], [0.0, 2.0, 0.0]])
    for end, want in ((np.array([3.0, 0.0, 0.0]), [True, True, True, False]),
                      (np.array([0.9, 0.0, 0.0]), [False, False, True, False])):
        got = np.empty(4, bool)
        K.segments_meet_boxes(ends, end, *box, got)
        assert got.tolist() == want, (end, got)


def test_image_taps_and_encode_taps():
    from sonicverse_core.acoustics.early import lattice

    q, m, _ = lattice(1)
    Kn = len(q)
    lo, hi = np.array([0.0, 0, 0]), np.array([6.0, 5, 3])
    src = np.array([[1.0, 1, 1.2], [4.0, 2, 1.0], [20.0, 2, 1.0]])  # the last is outside the box: no images
    lis = np.array([3.0, 2.5, 1.6])
    R = np.eye(3)
    amp = RNG.uniform(0.3, 0.9, Kn)
    occ = np.ones((3, 9))
    occ[1, 4:7] = [0.4, 0.5, 0.6]  # the images scale by the mid-band mean
    delay, gain, Y = np.empty((3, Kn)), np.empty((3, Kn)), np.empty((3, Kn, 9))
    K.image_taps(src, lo, hi, q, m, amp, lis, R, 0, 1.0, 500.0, 0.0, occ, 0.001, 343.0, delay, gain, Y)
    L = hi - lo
    img = (1 - 2 * q[None]) * (src[:2, None] - lo) + 2 * m[None] * L + lo - lis  # (2, K, 3)
    d = np.linalg.norm(img, axis=-1)
    g = _distance_twin(d, 0, 1.0, 500.0, 0.0) * amp[None] * occ[:2, 4:7].mean(1)[:, None]
    np.testing.assert_allclose(gain[:2], np.where(g >= 1e-4, g, 0), rtol=1e-12)
    np.testing.assert_allclose(delay[:2], d / 343.0 + 0.001, rtol=1e-12)
    u = img / d[..., None]
    x, y, z = u[..., 0], u[..., 1], u[..., 2]
    s3, s15 = np.sqrt(3), np.sqrt(15)
    Yref = np.stack([np.ones_like(x), s3 * y, s3 * z, s3 * x, s15 * x * y, s15 * y * z,
                     np.sqrt(5) / 2 * (3 * z * z - 1), s15 * x * z, s15 / 2 * (x * x - y * y)], -1)
    np.testing.assert_allclose(Y[:2], Yref, atol=1e-12)
    assert np.all(gain[2] == 0) and np.all(Y[2] == 0)

    # encode_taps: amb[c, t] = sum_ik tap_ik(t) (Y_old + (Y_new - Y_old) ramp)
    B, Hn = 64, 4096
    ring = RNG.normal(size=(3, Hn)).astype(np.float32)
    d_new = delay + RNG.uniform(-1e-5, 1e-5, delay.shape)
    g_new = gain * 0.9
    Y_new = Y * 0.95
    ramp = ((np.arange(B) + 1) / B).astype(np.float32)
    amb = np.empty((9, B), np.float32)
    K.encode_taps(ring, 100, delay, d_new, FS, gain, g_new, Y, Y_new, ramp, amb, np.empty(B, np.float32))
    t = np.arange(B)
    r = (t + 1) / B
    ref = np.zeros((9, B))
    for i in range(3):
        for k in range(Kn):
            if gain[i, k] == 0 and g_new[i, k] == 0:
                continue
            pos = 100 + t - (delay[i, k] + (d_new[i, k] - delay[i, k]) * r) * FS
            j = np.floor(pos).astype(int)
            fr = pos - j
            tap = (ring[i, j % Hn] * (1 - fr) + ring[i, (j + 1) % Hn] * fr) * (gain[i, k] + (g_new[i, k] - gain[i, k])
                                                                              * r)
            ref += tap[None] * (Y[i, k][:, None] + (Y_new[i, k] - Y[i, k])[:, None] * r[None])
    np.testing.assert_allclose(amb, ref, rtol=1e-3, atol=2e-4)


def test_barycentric_matches_an_exhaustive_search():
    from assets_manifest.hrtf import kemar
    from sonicverse_core.acoustics.hrtf import HrtfInterpolator

    h = HrtfInterpolator(kemar(), 48000, taps=64)
    d = RNG.normal(size=(300, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    grid, step = h._grid()
    idx, w = np.empty((len(d), 3), np.int64), np.empty((len(d), 3))
    K.barycentric(d, grid, step, h._inv, h._tri, idx, w)
    # twin: the triangle whose smallest barycentric weight is largest, over all triangles
    wa = np.einsum("tij,mj->mti", h._inv, d)
    best = np.argmax(wa.min(2), axis=1)
    ref_w = np.maximum(wa[np.arange(len(d)), best], 0)
    ref_w /= ref_w.sum(1, keepdims=True)
    same = np.all(np.sort(idx, 1) == np.sort(h._tri[best], 1), axis=1)
    assert same.mean() > 0.99  # a direction on an edge may pick either neighbour
    np.testing.assert_allclose(np.einsum("mk,mkj->mj", w[same], h.directions[idx[same]]) /
                               np.linalg.norm(np.einsum("mk,mkj->mj", w[same], h.directions[idx[same]]), axis=1,
                                              keepdims=True), d[same], atol=0.02)
    order = np.argsort(idx[same], 1)
    np.testing.assert_allclose(np.take_along_axis(w[same], order, 1),
                               np.take_along_axis(ref_w[same], np.argsort(h._tri[best][same], 1), 1), atol=1e-9)


@pytest.mark.parametrize("spec", ["builtin:l-room", "builtin:two-rooms?door=open"])
def test_room_image_taps_keep_exactly_the_specular_paths_the_mesh_leaves_open(spec):
    """Twin of room_image_taps, order 2, in the L-shaped room and in two rooms joined by a doorway: images by
    mirroring, reflection points by tracing back, each kept when its reflection points lie on their surfaces and
    every leg is free of the mesh (Embree rays through the real walls and doorway, not the kernel's plan tests and
    sampled openings); gains, delays and directions as the docstring says. Sources outside the rooms and unheard
    ones have no images; an image that appears starts at its own delay."""
    from sonicverse_core.acoustics.early import RoomImages, RoomWalls
    from sonicverse_core.geometry.raycast import SceneRayCaster
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene(spec)
    caster = SceneRayCaster(scene)
    g = RoomImages([RoomWalls(room, caster, [o for o in scene.objects if hasattr(o, "hinge")])
                    for room in scene.rooms], 2)
    E = len(g.edges)
    two = len(scene.rooms) == 2
    if two:
        src = np.array([[2.0, 2.6, 1.5], [1.0, 3.0, 1.0], [6.5, 1.0, 1.4], [9.0, 2.0, 1.5], [3.0, 1.0, 1.0]])
        listeners = (np.array([6.0, 1.7, 1.5]), np.array([6.0, 0.6, 1.5]), np.array([2.5, 2.0, 1.6]))
    else:
        src = np.array([[5.0, 1.5, 1.5], [1.5, 5.0, 1.2], [2.0, 2.0, 0.5], [4.5, 4.5, 1.5], [1.0, 1.0, 1.0]])
        listeners = (np.array([1.5, 1.5, 1.5]), np.array([1.2, 5.2, 1.7]), np.array([5.5, 0.5, 2.0]))
    mute = np.array([False, False, False, False, True])  # [3] is outside the rooms
    n, M = len(src), len(g.seqs)
    rng = np.random.default_rng(3)
    kept = wrong = 0
    for lis in listeners:
        R = np.eye(3)
        delay, gain, Y = np.zeros((n, M)), np.zeros((n, M)), np.zeros((n, M, 9))
        dp, gp, Yp = rng.uniform(0, 0.01, (n, M)), np.zeros((n, M)), rng.normal(size=(n, M, 9))
        EK.room_image_taps(src, mute, g.seqs, g.edges, g.normal, g.table, g.zwall, g.first, g.zf, g.zc, g.rf, g.rc,
                           lis, R, 0, 1.0, 500.0, 0.0, 0.001, 343.0, np.zeros((3, 3)), delay, gain, Y, dp, gp, Yp)
        for i in range(n):
            for k in range(M):
                seq = [p for p in g.seqs[k] if p >= 0]
                imgs = [src[i].copy()]
                for p in seq:  # mirror in the reflector's plane
                    x = imgs[-1].copy()
                    if p < E:
                        a, nrm = g.edges[p, :2], g.normal[p]
                        x[:2] -= 2 * np.dot(x[:2] - a, nrm) * nrm
                    else:
                        r = (p - E) // 2
                        x[2] = 2 * (g.zf[r] if (p - E) % 2 == 0 else g.zc[r]) - x[2]
                    imgs.append(x)
                ok, amp, pts = i < 3, 1.0, [lis]
                for j in range(len(seq), 0, -1):  # back from the listener
                    p, a_, b_ = seq[j - 1], pts[-1], imgs[j]
                    if p < E:
                        e0, nrm = g.edges[p, :2], g.normal[p]
                        hp, hb = np.dot(a_[:2] - e0, nrm), np.dot(b_[:2] - e0, nrm)
                    else:
                        r, floor = (p - E) // 2, (p - E) % 2 == 0
                        z0 = g.zf[r] if floor else g.zc[r]
                        hp, hb = (z0 - a_[2], z0 - b_[2]) if floor else (a_[2] - z0, b_[2] - z0)
                    if not hp < 0 < hb:
                        ok = False
                        break
                    q = a_ + hp / (hp - hb) * (b_ - a_)
                    if p < E:
                        ev = g.edges[p, 2:] - g.edges[p, :2]
                        t = np.dot(q[:2] - g.edges[p, :2], ev) / np.dot(ev, ev)
                        # a surface there: a ray from 5 cm in front meets it within 10 cm
                        h = caster.static.first_hit((q + 0.05 * np.r_[-g.normal[p], 0])[None],
                                                    np.r_[g.normal[p], 0][None], 0.1)
                        ok &= bool(0 <= t <= 1 and h.hit[0])
                        amp *= g.table.max()
                    else:
                        ok &= bool(scene.rooms[(p - E) // 2].contains(q[None, :2])[0])
                        amp *= g.rf[(p - E) // 2] if (p - E) % 2 == 0 else g.rc[(p - E) // 2]
                    pts.append(q)
                pts.append(src[i])
                if ok:  # every leg free of the structure (an open door's leaf is no obstacle to the images): rays stop
                    # 2 cm short of each end
                    for a_, b_ in zip(pts[:-1], pts[1:]):
                        v = b_ - a_
                        L = np.linalg.norm(v)
                        h = caster.static.first_hit(a_[None] + 0.02 * v / L, (v / L)[None], L - 0.04)
                        ok &= not h.hit[0]
                d = np.linalg.norm(imgs[-1] - lis)
                want = _distance_twin(d, 0, 1.0, 500.0, 0.0) * amp if ok else 0.0
                if (gain[i, k] > 0) != (want >= 1e-4):
                    wrong += 1
                    continue
                if gain[i, k] > 0:
                    kept += 1
                    if not two:  # one material everywhere: the factors are exact
                        assert gain[i, k] == pytest.approx(want, rel=1e-9), (i, k, seq)
                    assert delay[i, k] == pytest.approx(d / 343.0 + 0.001, rel=1e-12)
                    u = (imgs[-1] - lis) / d
                    assert Y[i, k, 3] == pytest.approx(np.sqrt(3) * u[0]) and Y[i, k, 1] == pytest.approx(
                        np.sqrt(3) * u[1])
                    assert dp[i, k] == delay[i, k] and np.array_equal(Yp[i, k], Y[i, k])  # appeared: no sweep
    assert kept > 60  # the comparison saw plenty of images
    # the kernel samples walls every 1/128 of their length and 1/8 of their height: a path grazing a jamb or
    # running into a corner may fall the other way
    assert wrong <= (0 if not two else 0.03 * kept), (wrong, kept)


def test_occlusion_logs_match_the_crossings_twin():
    """The occlusion recast's reduction of a walk's hits, against the NumPy path it replaced: the walk's crossings
    sorted by distance, a sounding object's own parts left out (``own_object_crossings``), each part once per
    segment at its nearest crossing, its material's log transmission summed. Segments through walls, doors and
    objects of a home, some starting inside an object (its sound position), the hits in shuffled order."""
    from sonicverse_core.acoustics.occlusion import own_object_crossings, sounding_bounds
    from sonicverse_core.geometry.raycast import SceneRayCaster
    from sonicverse_core.scene import load_scene
    from sonicverse_core.scene.materials import material_arrays

    s = load_scene("builtin:apartment?seed=0")
    rc = SceneRayCaster(s)
    lo, hi = s.bounds
    rng = np.random.default_rng(5)
    objs = [o.sound_position() for o in s.objects if o.world_bounds() is not None][:20]
    a = np.concatenate([np.array(objs), rng.uniform(lo, hi, (60, 3))])
    a[len(objs):, 2] = rng.uniform(0.3, 2.0, 60)
    b = rng.uniform(lo, hi, (len(a), 3))
    b[:, 2] = 1.6
    log_trans = 0.5 * np.log(np.maximum(material_arrays()[2], 1e-12))
    bounds = sounding_bounds(s)
    off = rc.part_offset()
    cr = rc.crossings(a, b)
    keep = ~own_object_crossings(bounds, off, cr, a)
    ray, part, mat = cr.ray[keep], cr.part[keep], cr.material[keep]
    _, first = np.unique(ray * (int(part.max()) + 1) + part, return_index=True)
    want = np.zeros((len(a), log_trans.shape[1]))
    np.add.at(want, ray[first], log_trans[mat[first]])
    assert (~keep).sum() >= 5 and len(first) < keep.sum() and (want < 0).any(axis=1).sum() >= 20  # all cases met
    ray, dist, face, ci, casters = rc.walk(a, b)
    order = rng.permutation(len(ray))
    sm, dm = casters[0][0].mesh, casters[1][0].mesh
    got = np.full_like(want, 9.0)
    K.occlusion_logs(ray[order], dist[order], face[order], ci[order], sm.face_part, sm.face_material, dm.face_part,
                     dm.face_material, off, bounds, a, log_trans, got)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_every_kernel_has_a_twin():
    """A kernel added without a twin fails here."""
    import inspect

    here = "".join(open(__file__.replace("test_kernels.py", f)).read()
                   for f in ("test_kernels.py", "test_late_kernels.py", "test_engine.py", "test_long_tail.py"))
    # K's private _tap and _tap_runs (inside gather's twin), _wrap_copy (read_sources' and late_send's),
    # _crossed_part (occlusion_logs'), _image, _sh9 (image_taps' and room_image_taps' twins); LK's _ring_fade
    # (inside late_send's); EK's _blocked and _inside (inside room_image_taps' twin)
    for mod, prefix, private in ((K, "K", 6), (LK, "LK", 1), (EK, "EK", 2)):
        kernels = {n for n, f in vars(mod).items() if hasattr(f, "py_func") and not n.startswith("_")
                   and f.__module__ == mod.__name__}
        missing = sorted(n for n in kernels if f"{prefix}.{n}(" not in here and f"import {n}" not in here)
        assert not missing, missing
        assert inspect.getsource(mod).count("@njit") == len(kernels) + private


def test_no_kernel_makes_an_array():
    """The kernels run per block: none may allocate (the audio callback allocates no array memory; numba's own
    allocations are counted in tests/test_poison.py). A source scan of every compiled function's body."""
    import inspect

    from sonicverse_core.acoustics import path_kernels

    made = ("np.empty(", "np.zeros(", "np.ones(", "np.full(", "np.array(", ".copy()", "np.concatenate(", "np.stack(")
    per_block = [f for mod in (K, LK, EK) for f in vars(mod).values() if hasattr(f, "py_func")] + \
        [path_kernels.combine_paths, path_kernels._unit]
    bad = [(f.__name__, m) for f in per_block for m in made if m in inspect.getsource(f.py_func).split('"""')[-1]]
    assert not bad, bad


def test_nearest_direction():
    dirs = RNG.normal(size=(40, 3))
    meas = RNG.normal(size=(25, 3))
    meas /= np.linalg.norm(meas, axis=1, keepdims=True)
    idx, w = np.empty((40, 3), np.int64), np.empty((40, 3))
    K.nearest_direction(dirs, meas, idx, w)
    ref = np.argmax(dirs @ meas.T, axis=1)
    assert np.all(idx == ref[:, None]) and np.all(w == [1.0, 0.0, 0.0])


def test_onset_delays_and_pan_spectra():
    n = 5
    w = RNG.dirichlet(np.ones(3), n)
    idx = RNG.integers(0, 10, (n, 3))
    onsets = RNG.uniform(0, 1e-3, (10, 2))
    d0, spread, mean = RNG.uniform(0, 0.05, n), RNG.uniform(0, 1, n), onsets.mean(0)
    out = np.empty((n, 2))
    K.onset_delays(w, idx, onsets, d0, spread, mean, out)
    o = np.einsum("mk,mke->me", w, onsets[idx])
    np.testing.assert_allclose(out, d0[:, None] + o + (mean[None] - o) * spread[:, None], rtol=1e-12)
    dirs = RNG.normal(size=(n, 3))
    curve = RNG.uniform(0, 1, (n, 7)).astype(np.float32)
    spec = np.empty((n, 2, 7), np.complex64)
    for mono in (False, True):
        K.pan_spectra(dirs, curve, mono, spec)
        y = dirs[:, 1] / np.linalg.norm(dirs, axis=1)
        pan = np.full((n, 2), np.sqrt(0.5)) if mono else np.stack([np.sqrt(0.5 * (1 + y)), np.sqrt(0.5 * (1 - y))], 1)
        np.testing.assert_allclose(spec, pan[:, :, None] * curve[:, None, :], rtol=1e-6)


def test_woodworth_delays():
    """The stereo panner's per-ear delays against Woodworth's formula written out in NumPy."""
    n, ac = 50, 0.0875 / 343.0
    dirs = RNG.normal(size=(n, 3))
    dirs[0] = [0, 0, 0]  # a source at the head: no interaural delay
    d0 = RNG.uniform(0, 0.05, n)
    out = np.empty((n, 2))
    K.woodworth_delays(dirs, d0, ac, out)
    r = np.linalg.norm(dirs, axis=1)
    th = np.arcsin(np.divide(dirs[:, 1], r, out=np.zeros(n), where=r > 0))
    itd = ac * (th + np.sin(th))
    np.testing.assert_allclose(out[:, 1] - out[:, 0], itd, atol=1e-15)
    np.testing.assert_allclose(out.mean(1), d0 + 0.5 * ac * (np.pi / 2 + 1), atol=1e-15)
    assert np.all(out >= d0[:, None] - 1e-15)


def test_block_glue_kernels():
    """The small kernels that replace NumPy expressions in the renderer's block (each against that expression)."""
    n = 6
    occ, target = RNG.uniform(0, 1, (n, 9)), RNG.uniform(0, 1, (n, 9))
    fresh, mute = np.array([1, 0, 0, 1, 0, 0], bool), np.array([0, 0, 1, 1, 0, 0], bool)
    ref = occ + 0.25 * (target - occ)
    ref[fresh] = target[fresh]
    ref[mute] = 0.0
    K.smooth_toward(occ, target, 0.75, fresh, mute)
    np.testing.assert_allclose(occ, ref, rtol=1e-12)

    h = RNG.normal(size=(4, 32))
    ref = h.copy()
    ref[:, :-8] = ref[:, 8:]
    K.shift_left(h, 8)
    np.testing.assert_array_equal(h, ref)

    B, N = 8, 32
    both = RNG.normal(size=(2, 2, N)).astype(np.float32)
    ramp = ((np.arange(B) + 1) / B).astype(np.float32)
    for xf in (True, False):
        out = np.ones((2, B))
        K.crossfade_into(both, ramp, 0.5, xf, out)
        y0, y1 = both[0, :, -B:], both[1, :, -B:]
        np.testing.assert_allclose(out, 1 + 0.5 * ((y0 + (y1 - y0) * ramp) if xf else y1), rtol=1e-6)
    out = np.ones((2, B))
    K.add_tail(both[0], 2.0, out)
    np.testing.assert_allclose(out, 1 + 2.0 * both[0, :, -B:], rtol=1e-6)
    out = np.zeros((2, B))
    LK.mix_ramped(both[0], 0.2, 0.6, 1.0, 0.5, 0.1, out)
    r = (np.arange(B) + 1) / B
    np.testing.assert_allclose(out, 0.1 * both[0, :, -B:] * (0.2 + 0.4 * r) * (1.0 - 0.5 * r), rtol=1e-6)

    assert K.all_finite(np.ones((2, 3))) and not K.all_finite(np.array([[1.0, np.nan]]))
    assert not K.all_finite(np.array([np.inf], np.float32))

    R = np.empty((3, 3))
    K.head_rotation(30.0, 10.0, R)
    c, s_, cp, sp = np.cos(np.radians(30)), np.sin(np.radians(30)), np.cos(np.radians(10)), np.sin(np.radians(10))
    np.testing.assert_allclose(R, np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]]) @
                               np.array([[c, s_, 0], [-s_, c, 0], [0, 0, 1.0]]), atol=1e-12)

    a, b = RNG.uniform(0, 1, (n, 3)), RNG.uniform(0, 1, (n, 3))
    b[1] = a[1] + 0.01
    b[2, 0] = np.nan
    mask = np.empty(n, bool)
    cnt = K.rows_moved(a, b, 0.05, mask)
    np.testing.assert_array_equal(mask, ~(np.max(np.abs(a - b), axis=1) <= 0.05))
    assert cnt == mask.sum()
    assert K.farther(a[0], b[0], 0.0) == bool(np.any(a[0] != b[0])) and not K.farther(a[1], b[1], 0.05)
    assert K.farther(a[2], b[2], 10.0)  # NaN counts as moved
    x = RNG.uniform(0, 1, 50)
    assert K.count_over(x, 0.3) == np.count_nonzero(x > 0.3)

    room = np.array([-1, 0, 2, 1, 0])
    group, use = np.empty(5, np.int64), np.empty(5, bool)
    LK.late_groups(room, 0, group, use)
    np.testing.assert_array_equal(group, np.where((room >= 0) & (room != 0), room + 1, 0))
    np.testing.assert_array_equal(use, room < 0)
    send = np.array([0.0, 0.1, 0.2, 0.0, 0.3])
    assert LK.groups_sending(group, send, np.zeros(4, bool)) == len(np.unique(group[send > 0]))

    xs, prev = np.zeros((3, 8), np.float32), np.zeros((3, 8), np.float32)
    xs[0, 3], prev[2, 0] = 1.0, 0.5
    live = np.empty(3, bool)
    assert LK.live_rows(xs, prev, live) == 2
    np.testing.assert_array_equal(live, np.any(xs != 0, 1) | np.any(prev != 0, 1))
    X = (RNG.normal(size=(3, 5)) + 1j * RNG.normal(size=(3, 5))).astype(np.complex64)
    curves = RNG.uniform(0, 1, (3, 5)).astype(np.float32)
    row = np.empty(5, np.complex64)
    for shaped in (True, False):
        LK.fdl_fill(X, curves, live, shaped, row)
        np.testing.assert_allclose(row, ((X * curves) if shaped else X)[live].sum(0), rtol=1e-5)

    pend, ring_row = RNG.normal(size=16).astype(np.float32), np.empty(16, np.float32)
    K.scale_into(pend, 0.3, ring_row)
    np.testing.assert_allclose(ring_row, pend * np.float32(0.3), rtol=1e-6)
    s0, t1, cur = RNG.normal(size=7), RNG.normal(size=7), np.empty(7)
    K.lerp(s0, t1, 0.3, cur)
    np.testing.assert_allclose(cur, s0 + (t1 - s0) * 0.3, rtol=1e-12)
