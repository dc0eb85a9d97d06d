"""Every compiled kernel of the propagation paths (sonicverse_core/acoustics/path_kernels.py) against a NumPy twin
written from its docstring (the renderer's kernels are in test_kernels.py; a kernel without a twin fails
``test_every_path_kernel_has_a_twin``)."""
import numpy as np
import pytest
from scipy.sparse.csgraph import shortest_path as sp_shortest
from scipy.spatial.transform import Rotation

from sonicverse_core.acoustics import path_kernels as P
from sonicverse_core.acoustics.paths import path_graph
from sonicverse_core.acoustics.kernels import distance_gain_1
from sonicverse_core.scene.materials import BANDS

RNG = np.random.default_rng(15)


def _los_twin(blocked, x0, y0, x1, y1, samples=20000):
    """Dense sampling of the segment: every cell it passes through, but its two ends' cells, must be free and
    inside the grid."""
    t = np.linspace(0, 1, samples)
    j, i = np.floor(x0 + (x1 - x0) * t).astype(int), np.floor(y0 + (y1 - y0) * t).astype(int)
    ends = ((i == int(np.floor(y0))) & (j == int(np.floor(x0)))) | ((i == int(np.floor(y1))) & (j == int(np.floor(x1))))
    i, j = i[~ends], j[~ends]
    ny, nx = blocked.shape
    if np.any((i < 0) | (j < 0) | (i >= ny) | (j >= nx)):
        return False
    return not blocked[i, j].any()


def _crosses_twin(a, b, c, d):
    """Proper intersection: a + t (b - a) = c + u (d - c) with t, u strictly inside (0, 1)."""
    M = np.array([[b[0] - a[0], c[0] - d[0]], [b[1] - a[1], c[1] - d[1]]])
    if abs(np.linalg.det(M)) < 1e-15:
        return False
    t, u = np.linalg.solve(M, np.asarray(c, float) - np.asarray(a, float))
    return 0 < t < 1 and 0 < u < 1


def test_grid_los_and_crosses():
    blocked = RNG.uniform(size=(24, 24)) < 0.12
    agree, total = 0, 0
    for _ in range(400):
        x0, y0, x1, y1 = RNG.uniform(0.01, 23.99, 4)
        agree += P.grid_los(blocked, x0, y0, x1, y1) == _los_twin(blocked, x0, y0, x1, y1)
        total += 1
    assert agree / total > 0.99, agree / total  # sampling can miss a corner clipped by under 1e-3 of a cell
    # a wall between, a clear row, and the ends' own cells never count
    wall = np.zeros((10, 10), bool)
    wall[:, 5] = True
    assert not P.grid_los(wall, 1.5, 2.5, 8.5, 2.5) and P.grid_los(wall, 1.5, 2.5, 4.5, 7.5)
    assert P.grid_los(wall, 5.5, 2.5, 5.5, 2.5)
    # diagonal crack: both side cells blocked, the segment through their shared corner is blocked
    crack = np.zeros((4, 4), bool)
    crack[1, 2] = crack[2, 1] = True
    assert not P.grid_los(crack, 1.5, 1.5, 2.5, 2.5)
    for _ in range(300):
        a, b, c, d = RNG.uniform(0, 1, (4, 2))
        assert P._crosses(*a, *b, *c, *d) == _crosses_twin(a, b, c, d)


def test_visible_nodes_and_door_factor():
    blocked = RNG.uniform(size=(30, 30)) < 0.08
    origin, cell = np.array([-1.0, 2.0]), 0.1
    nodes = origin + RNG.uniform(0.05, 2.95, (40, 2))
    doors = np.tile(origin, 2) + RNG.uniform(0.05, 2.95, (3, 4))
    closed = np.array([True, False, True])
    p = origin + np.array([1.5, 1.5])
    out = np.empty(40, bool)
    P.visible_nodes(blocked, origin, cell, p, nodes, doors, closed, out)
    g = (p - origin) / cell
    ref = [_los_twin(blocked, *g, *((nd - origin) / cell)) and
           not any(closed[k] and _crosses_twin(p, nd, doors[k, :2], doors[k, 2:]) for k in range(3)) for nd in nodes]
    assert np.mean(out == np.array(ref)) > 0.97
    aperture = np.array([0.3, 1.0, 0.5])
    for _ in range(100):
        a, b = origin + RNG.uniform(0, 3, (2, 2))
        ref = np.prod([aperture[k] for k in range(3) if aperture[k] < 1 and
                       _crosses_twin(a, b, doors[k, :2], doors[k, 2:])])
        assert P._door_factor(*a, *b, doors, aperture) == pytest.approx(ref)


def test_shortest_path():
    N = 12
    nodes = RNG.uniform(0, 10, (N, 2))
    adj = np.hypot(*(nodes[:, None] - nodes[None]).transpose(2, 0, 1)) * (RNG.uniform(size=(N, N)) < 0.35)
    adj = np.maximum(adj, adj.T)
    dist, pred = sp_shortest(adj, directed=False, return_predecessors=True)
    for _ in range(50):
        s, lis = RNG.uniform(0, 10, (2, 2))
        vs, vl = RNG.uniform(size=N) < 0.3, RNG.uniform(size=N) < 0.3
        chain = np.empty(64, np.int64)
        m, L = P.shortest_path(s, lis, vs, vl, nodes, dist, pred.astype(np.int32), chain)
        ds = np.where(vs, np.hypot(*(nodes - s).T), np.inf)
        dl = np.where(vl, np.hypot(*(nodes - lis).T), np.inf)
        tot = ds[:, None] + dist + dl[None, :]
        if not np.isfinite(tot).any():
            assert m == 0 and L == np.inf
            continue
        assert L == pytest.approx(tot.min())
        c = chain[:m]
        assert vs[c[0]] and vl[c[-1]]
        legs = np.hypot(*(nodes[c[1:]] - nodes[c[:-1]]).T).sum() if m > 1 else 0.0
        assert np.hypot(*(nodes[c[0]] - s)) + legs + np.hypot(*(nodes[c[-1]] - lis)) == pytest.approx(L)


def test_trace_paths_matches_its_formula_in_two_rooms():
    """Per source without line of sight: the twin's shortest path over the graph, its bends' Fresnel losses
    min(10 log10(1 + 40 delta f / c), 25) dB and the doorways' apertures."""
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene("builtin:two-rooms?door=open")
    scene.set_door(scene.doors[0].name, 0.4)  # a part-open leaf: an obstacle and an aperture below 1
    g = path_graph(scene)
    g.refresh()
    lo, hi = scene.bounds[0, :2] + 0.3, scene.bounds[1, :2] - 0.3
    pts = RNG.uniform(lo, hi, (60, 2))
    lis = np.array([*RNG.uniform(lo, hi), 1.5])
    pos = np.c_[pts, np.full(60, 1.2)]
    vis = np.array([g.visible(p) for p in pts])
    on, length = np.zeros(60, bool), np.zeros(60)
    last, first, amp = np.zeros((60, 2)), np.zeros((60, 2)), np.zeros((60, 9))
    P.trace_paths(np.arange(60), pos, lis, vis, g.visible(lis[:2]), g.blocked, g.origin, g.cell, g.nodes, g.dist,
                  g.pred, g.leaves, g.door_segments, g.aperture, BANDS, 343.0, True, on, length, last, first, amp)
    checked = 0
    for i in range(60):
        if g.line_of_sight(pts[i], lis[:2]):
            assert not on[i]
            continue
        ds = np.where(vis[i], np.hypot(*(g.nodes - pts[i]).T), np.inf)
        dl = np.where(g.visible(lis[:2]), np.hypot(*(g.nodes - lis[:2]).T), np.inf)
        tot = ds[:, None] + g.dist + dl[None, :]
        if not np.isfinite(tot).any():
            assert not on[i]
            continue
        assert on[i] and length[i] == pytest.approx(tot.min())
        a, b = np.unravel_index(np.argmin(tot), tot.shape)
        chain = [b]
        while chain[-1] != a:
            chain.append(g.pred[a, chain[-1]])
        pts_path = np.vstack([pts[i], g.nodes[chain[::-1]], lis[:2]])
        np.testing.assert_allclose(first[i], pts_path[1])
        np.testing.assert_allclose(last[i], pts_path[-2])
        loss = np.zeros(9)
        for k in range(1, len(pts_path) - 1):
            p0, q, r = pts_path[k - 1], pts_path[k], pts_path[k + 1]
            delta = np.hypot(*(q - p0)) + np.hypot(*(r - q)) - np.hypot(*(r - p0))
            loss += np.minimum(10 * np.log10(1 + 40 * max(delta, 0) * BANDS / 343.0), 25.0)
        f = np.prod([g.aperture[d] for d in range(len(g.door_segments)) for k in range(len(pts_path) - 1)
                     if g.aperture[d] < 1 and _crosses_twin(pts_path[k], pts_path[k + 1], g.door_segments[d, :2],
                                                           g.door_segments[d, 2:])])
        np.testing.assert_allclose(amp[i], 10 ** (-loss / 20) * np.sqrt(f), rtol=1e-9)
        checked += 1
    assert checked >= 10


def test_combine_paths_and_unit():
    assert P._unit(0.0, 0.0, 0.0) == (0.0, 0.0, 0.0)
    np.testing.assert_allclose(P._unit(3.0, 0.0, 4.0), (0.6, 0.0, 0.8))
    n = 8
    lis = np.array([1.0, 2.0, 1.6])
    pos = lis + RNG.uniform(-6, 6, (n, 3))
    fwd = RNG.normal(size=(n, 3))
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    on = np.array([1, 1, 1, 0, 1, 1, 1, 1], bool)
    trans = RNG.uniform(0.01, 0.5, (n, 9))
    plen = np.linalg.norm((pos - lis)[:, :2], axis=1) * RNG.uniform(1.1, 1.6, n)
    last = lis[:2] + RNG.uniform(-2, 2, (n, 2))
    first = pos[:, :2] + RNG.uniform(-2, 2, (n, 2))
    pamp = RNG.uniform(0.05, 0.9, (n, 9))
    rel0 = RNG.normal(size=(n, 3))
    fresh = np.array([1, 0, 1, 0, 0, 1, 0, 0], bool)
    k, roll = 0.75, (0, 1.0, 500.0, 1 / 3)
    target, eff, f, rel = np.ones((n, 9)), pos.copy(), fwd.copy(), rel0.copy()
    count = P.combine_paths(on, pos, fwd, lis, trans, plen, last, first, pamp, rel, fresh, k, *roll, target, eff, f)
    assert count == on.sum()

    def unit(v):
        return v / np.linalg.norm(v)

    for i in range(n):
        s = pos[i] - lis
        if not on[i]:
            np.testing.assert_allclose(rel[i], s)
            np.testing.assert_array_equal(target[i], 1.0)
            continue
        d, dz = np.linalg.norm(s), s[2]
        Lp = np.hypot(plen[i], dz)
        lv = last[i] - lis[:2]
        u_p, u_t = unit(np.array([*lv, dz * np.linalg.norm(lv) / plen[i]])), unit(s)
        gp, gt = distance_gain_1(Lp, *roll), distance_gain_1(d, *roll)
        wp, wt = np.sum((gp * pamp[i, 4:7]) ** 2), np.sum((gt * trans[i, 4:7]) ** 2)
        wp, wt = wp / (wp + wt), wt / (wp + wt)
        Lb = wp * Lp + wt * d
        np.testing.assert_allclose(target[i], np.hypot(gp * pamp[i], gt * trans[i]) / distance_gain_1(Lb, *roll),
                                   rtol=1e-9)
        rt = unit(wp * u_p + wt * u_t) * Lb
        ref_rel = rt if fresh[i] else rel0[i] + (1 - k) * (rt - rel0[i])
        np.testing.assert_allclose(rel[i], ref_rel, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(eff[i], lis + ref_rel, rtol=1e-9)
        fl = first[i] - pos[i, :2]
        e = unit(wp * unit(np.array([*fl, -dz * np.linalg.norm(fl) / plen[i]])) - wt * u_t)
        v = -unit(ref_rel)
        rot = Rotation.align_vectors([v], [e])[0]  # the smallest rotation taking e to v
        np.testing.assert_allclose(f[i], rot.apply(fwd[i]), atol=1e-7)


def test_every_path_kernel_has_a_twin():
    import inspect

    kernels = {n for n, f in vars(P).items() if hasattr(f, "py_func") and f.__module__ == P.__name__}
    here = open(__file__).read()
    missing = sorted(n for n in kernels if f"P.{n}(" not in here)
    assert not missing, missing
    assert inspect.getsource(P).count("@njit") == len(kernels)
