"""The propagation paths' compiled kernels (:mod:`sonicverse_core.acoustics.paths` bakes the graph and runs them;
``tests/test_path_kernels.py`` checks each against a NumPy twin): line of sight on the ear-height grid, the nodes a
point sees, the shortest path over them with its bends' diffraction loss and doors' apertures, and the per-block
blend of a path with the straight-line transmission into one emitter per source."""
from __future__ import annotations

import numpy as np
from numba import njit

from sonicverse_core.acoustics.kernels import distance_gain_1

_opts = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")

MAX_BEND_LOSS_DB = 25.0


@njit(**_opts)
def grid_los(blocked, x0, y0, x1, y1):
    """True when the segment (x0, y0) -> (x1, y1) (in cell units, cell (i, j) spans [j, j+1) x [i, i+1)) meets no
    blocked cell other than the cells of its two ends. Exact traversal (Amanatides & Woo); where the segment passes
    through a cell corner both side cells must be free (no leak through diagonal cracks)."""
    ny, nx = blocked.shape
    j, i = int(np.floor(x0)), int(np.floor(y0))
    je, ie = int(np.floor(x1)), int(np.floor(y1))
    dx, dy = x1 - x0, y1 - y0
    sx = 1 if dx > 0 else -1
    sy = 1 if dy > 0 else -1
    tdx = abs(1.0 / dx) if dx != 0 else np.inf
    tdy = abs(1.0 / dy) if dy != 0 else np.inf
    tx = ((j + 1 - x0) if dx > 0 else (x0 - j)) * tdx if dx != 0 else np.inf
    ty = ((i + 1 - y0) if dy > 0 else (y0 - i)) * tdy if dy != 0 else np.inf
    n = abs(je - j) + abs(ie - i)
    for _ in range(n + 2):
        if i == ie and j == je:
            return True
        if abs(tx - ty) < 1e-9:  # through a corner: both neighbours, then the diagonal
            for ci, cj in ((i, j + sx), (i + sy, j)):
                if not (ci == ie and cj == je) and 0 <= ci < ny and 0 <= cj < nx and blocked[ci, cj]:
                    return False
            i += sy
            j += sx
            tx += tdx
            ty += tdy
        elif tx < ty:
            j += sx
            tx += tdx
        else:
            i += sy
            ty += tdy
        if i == ie and j == je:
            return True
        if i < 0 or j < 0 or i >= ny or j >= nx:
            return False
        if blocked[i, j]:
            return False
    return True


@njit(**_opts)
def _crosses(ax, ay, bx, by, cx, cy, dx, dy):
    """Do segments ab and cd cross (proper intersection)?"""
    d1 = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    d2 = (bx - ax) * (dy - ay) - (by - ay) * (dx - ax)
    d3 = (dx - cx) * (ay - cy) - (dy - cy) * (ax - cx)
    d4 = (dx - cx) * (by - cy) - (dy - cy) * (bx - cx)
    return d1 * d2 < 0 and d3 * d4 < 0


@njit(**_opts)
def visible_nodes(blocked, origin, cell, p, nodes, doors, closed, out):
    """out[k]: node k is in line of sight of point p (2,) on the grid, crossing none of the segments ``doors``
    (d, 4) whose ``closed`` flag is set (the door leaves where they are now)."""
    x0, y0 = (p[0] - origin[0]) / cell, (p[1] - origin[1]) / cell
    for k in range(nodes.shape[0]):
        ok = grid_los(blocked, x0, y0, (nodes[k, 0] - origin[0]) / cell, (nodes[k, 1] - origin[1]) / cell)
        if ok:
            for d in range(doors.shape[0]):
                if closed[d] and _crosses(p[0], p[1], nodes[k, 0], nodes[k, 1], doors[d, 0], doors[d, 1],
                                          doors[d, 2], doors[d, 3]):
                    ok = False
                    break
        out[k] = ok


@njit(**_opts)
def _door_factor(ax, ay, bx, by, doors, aperture):
    f = 1.0
    for d in range(doors.shape[0]):
        if aperture[d] < 1.0 and _crosses(ax, ay, bx, by, doors[d, 0], doors[d, 1], doors[d, 2], doors[d, 3]):
            f *= aperture[d]
    return f


@njit(**_opts)
def shortest_path(s, lis, vis_s, vis_l, nodes, dist, pred, chain):
    """The shortest open path s -> a ... b -> lis (2-D points) through nodes seen from each end. Writes the node
    indices into chain and returns (their count, length); (0, inf) when there is none."""
    best, ba, bb = np.inf, -1, -1
    N = nodes.shape[0]
    ds = np.empty(N)
    dl = np.empty(N)
    for k in range(N):
        ds[k] = np.hypot(nodes[k, 0] - s[0], nodes[k, 1] - s[1]) if vis_s[k] else np.inf
        dl[k] = np.hypot(nodes[k, 0] - lis[0], nodes[k, 1] - lis[1]) if vis_l[k] else np.inf
    for a in range(N):
        if ds[a] == np.inf:
            continue
        for b in range(N):
            if dl[b] == np.inf:
                continue
            t = ds[a] + dist[a, b] + dl[b]
            if t < best:
                best, ba, bb = t, a, b
    if ba < 0:
        return 0, np.inf
    m = 0
    j = bb
    while j != ba and m < len(chain) - 1:
        chain[m] = j
        m += 1
        j = pred[ba, j]
        if j < 0:
            return 0, np.inf
    chain[m] = ba
    m += 1
    chain[:m] = chain[:m][::-1].copy()
    return m, best


@njit(**_opts)
def trace_paths(idx, pos, lis, vis_src, vis_l, blocked, origin, cell, nodes, dist, pred, leaves, doors, aperture,
                bands, c_sound, bend_loss, on, length, last, first, amp):
    """For the sources ``idx``: whether they reach the listener along a bent path (no line of sight on the slice
    and a path exists), its 2-D length, its last and first bend points (2,) and amplitude per band (diffraction at
    every bend x the square root of the doorways' aperture fractions)."""
    chain = np.empty(64, np.int64)
    lx, ly = (lis[0] - origin[0]) / cell, (lis[1] - origin[1]) / cell
    for i in idx:
        s = pos[i, :2]
        sees = grid_los(blocked, (s[0] - origin[0]) / cell, (s[1] - origin[1]) / cell, lx, ly)
        if sees:
            for d in range(leaves.shape[0]):
                if _crosses(s[0], s[1], lis[0], lis[1], leaves[d, 0], leaves[d, 1], leaves[d, 2], leaves[d, 3]):
                    sees = False
                    break
        on[i] = False
        if sees or nodes.shape[0] == 0:
            continue
        m, L = shortest_path(s, lis[:2], vis_src[i], vis_l, nodes, dist, pred, chain)
        if m == 0:
            continue
        on[i] = True
        length[i] = L
        first[i, 0], first[i, 1] = nodes[chain[0], 0], nodes[chain[0], 1]
        last[i, 0], last[i, 1] = nodes[chain[m - 1], 0], nodes[chain[m - 1], 1]
        f = 1.0
        for b in range(len(bands)):
            amp[i, b] = 0.0
        for k in range(m + 1):  # legs s -> n0, n0 -> n1, ..., n_{m-1} -> lis
            px, py = (s[0], s[1]) if k == 0 else (nodes[chain[k - 1], 0], nodes[chain[k - 1], 1])
            qx, qy = (lis[0], lis[1]) if k == m else (nodes[chain[k], 0], nodes[chain[k], 1])
            f *= _door_factor(px, py, qx, qy, doors, aperture)
            if bend_loss and k < m:  # the bend at node k: detour over the line between its neighbours
                rx, ry = (lis[0], lis[1]) if k == m - 1 else (nodes[chain[k + 1], 0], nodes[chain[k + 1], 1])
                delta = np.hypot(qx - px, qy - py) + np.hypot(rx - qx, ry - qy) - np.hypot(rx - px, ry - py)
                for b in range(len(bands)):
                    amp[i, b] += min(10.0 * np.log10(1.0 + 40.0 * max(delta, 0.0) * bands[b] / c_sound),
                                     MAX_BEND_LOSS_DB)
        for b in range(len(bands)):
            amp[i, b] = 10.0 ** (-amp[i, b] / 20.0) * np.sqrt(f)


@njit(**_opts)
def _unit(x, y, z):
    """(x, y, z) / |(x, y, z)|, or zeros for a null vector (scalars: no array per call)."""
    n = np.sqrt(x * x + y * y + z * z)
    if n < 1e-9:
        return 0.0, 0.0, 0.0
    return x / n, y / n, z / n


@njit(**_opts)
def combine_paths(on, pos, fwd, lis, trans, plen, last, first, pamp, rel, fresh, k, mode, d0, D, near_k,
                  target, eff, f):
    """Per source heard along a path: the path (amplitude pamp, 2-D length plen, last bend, first bend) and the
    straight-line transmission added in energy per band, heard from a virtual source at the energy-weighted blend
    of their directions and lengths (smoothed towards it by k per block unless fresh); the forward turned by the
    rotation taking the blended emission direction to the one the virtual source implies, so directivity acts on
    the path's first leg. Sources without a path keep their position (rel is reset to the straight line; their
    rows of target, eff and f are left as they are). Returns how many sources were heard along a path."""
    count = 0
    nb = trans.shape[1]
    for i in range(pos.shape[0]):
        sx, sy, sz = pos[i, 0] - lis[0], pos[i, 1] - lis[1], pos[i, 2] - lis[2]
        if not on[i]:
            rel[i, 0], rel[i, 1], rel[i, 2] = sx, sy, sz
            continue
        count += 1
        d = np.sqrt(sx * sx + sy * sy + sz * sz)
        dz = sz
        L2 = plen[i]
        Lp = np.sqrt(L2 * L2 + dz * dz)
        lx, ly = last[i, 0] - lis[0], last[i, 1] - lis[1]
        r_last = np.sqrt(lx * lx + ly * ly)
        px, py, pz = _unit(lx, ly, dz * r_last / max(L2, 1e-9))
        tx, ty, tz = _unit(sx, sy, sz)
        gp, gt = distance_gain_1(Lp, mode, d0, D, near_k), distance_gain_1(d, mode, d0, D, near_k)
        w_p, w_t = 0.0, 0.0
        for b in range(4, 7):
            w_p += (gp * pamp[i, b]) ** 2
            w_t += (gt * trans[i, b]) ** 2
        w = max(w_p + w_t, 1e-30)
        w_p, w_t = w_p / w, w_t / w
        ux, uy, uz = _unit(w_p * px + w_t * tx, w_p * py + w_t * ty, w_p * pz + w_t * tz)
        Lb = w_p * Lp + w_t * d
        gb = max(distance_gain_1(Lb, mode, d0, D, near_k), 1e-30)
        for b in range(nb):
            target[i, b] = np.sqrt((gp * pamp[i, b]) ** 2 + (gt * trans[i, b]) ** 2) / gb
        if fresh[i]:
            rel[i, 0], rel[i, 1], rel[i, 2] = ux * Lb, uy * Lb, uz * Lb
        else:
            rel[i, 0] += (1.0 - k) * (ux * Lb - rel[i, 0])
            rel[i, 1] += (1.0 - k) * (uy * Lb - rel[i, 1])
            rel[i, 2] += (1.0 - k) * (uz * Lb - rel[i, 2])
        eff[i, 0], eff[i, 1], eff[i, 2] = lis[0] + rel[i, 0], lis[1] + rel[i, 1], lis[2] + rel[i, 2]
        # emission: along the first leg (path) or straight at the listener (transmission), blended
        fx, fy = first[i, 0] - pos[i, 0], first[i, 1] - pos[i, 1]
        ex, ey, ez = _unit(fx, fy, -dz * np.sqrt(fx * fx + fy * fy) / max(L2, 1e-9))
        ex, ey, ez = _unit(w_p * ex - w_t * tx, w_p * ey - w_t * ty, w_p * ez - w_t * tz)
        vx, vy, vz = _unit(rel[i, 0], rel[i, 1], rel[i, 2])
        vx, vy, vz = -vx, -vy, -vz
        # Rodrigues: the rotation taking e to v, applied to the forward
        ax, ay, az = ey * vz - ez * vy, ez * vx - ex * vz, ex * vy - ey * vx
        sn = np.sqrt(ax * ax + ay * ay + az * az)
        c = ex * vx + ey * vy + ez * vz
        x0, x1, x2 = fwd[i, 0], fwd[i, 1], fwd[i, 2]
        if sn < 1e-9:
            if c > 0:
                f[i, 0], f[i, 1], f[i, 2] = x0, x1, x2
                continue
            if abs(ez) < 0.9:
                ax, ay, az = -ey, ex, 0.0
            else:
                ax, ay, az = 0.0, -ez, ey
            sn = 0.0
        kx, ky, kz = _unit(ax, ay, az)
        cx, cy, cz = ky * x2 - kz * x1, kz * x0 - kx * x2, kx * x1 - ky * x0
        kd = kx * x0 + ky * x1 + kz * x2
        f[i, 0] = x0 * c + cx * sn + kx * kd * (1.0 - c)
        f[i, 1] = x1 * c + cy * sn + ky * kd * (1.0 - c)
        f[i, 2] = x2 * c + cz * sn + kz * kd * (1.0 - c)
    return count
