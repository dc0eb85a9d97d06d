"""Compiled per-block kernels of the early reflections off rooms' own walls (:mod:`sonicverse_core.acoustics.early`):
image sources of vertical-walled rooms (footprint polygons, flat floors and ceilings) joined by openings, each
checked by tracing its path back from the listener (Borish 1984)."""
from __future__ import annotations

import numpy as np
from numba import njit

from sonicverse_core.acoustics.kernels import _sh9, distance_gain_1

_opts = dict(cache=True, nogil=True, fastmath=False, error_model="numpy")


@njit(**_opts)
def _inside(x, y, edges, a, b):
    """Whether the plan point (x, y) is inside the polygon whose sides are ``edges[a:b]`` (even-odd rule)."""
    inside = False
    for e in range(a, b):
        x0, y0, x1, y1 = edges[e, 0], edges[e, 1], edges[e, 2], edges[e, 3]
        if (y0 > y) != (y1 > y) and x < x0 + (y - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    return inside


@njit(**_opts)
def _blocked(ax, ay, az, bx, by, bz, edges, table, zwall, skip0, skip1):
    """Whether the leg (ax, ay, az)-(bx, by, bz) meets a wall of ``edges`` (E, 4) other than walls skip0 and skip1
    (the walls its ends lie on; -1: none) where the wall is solid: it properly crosses the wall in plan, between
    the wall's floor and ceiling (``zwall`` (E, 2)) where its sampled factor (``table`` (E, T, Z)) is not 0, or
    above or below it. Touching a wall's end or running along it is no crossing (1 mm tolerance), so a path may
    graze the corner it turns round."""
    eps = 1e-3
    T, Z = table.shape[1], table.shape[2]
    for e in range(edges.shape[0]):
        if e == skip0 or e == skip1:
            continue
        cx, cy, dx, dy = edges[e, 0], edges[e, 1], edges[e, 2], edges[e, 3]
        ux, uy = bx - ax, by - ay
        vx, vy = dx - cx, dy - cy
        den = ux * vy - uy * vx
        if abs(den) < 1e-12:
            continue  # parallel
        wx, wy = cx - ax, cy - ay
        s = (wx * vy - wy * vx) / den  # along the leg
        t = (wx * uy - wy * ux) / den  # along the wall
        lu = np.sqrt(ux * ux + uy * uy)
        lv = np.sqrt(vx * vx + vy * vy)
        if s * lu > eps and (1.0 - s) * lu > eps and t * lv > eps and (1.0 - t) * lv > eps:
            z = az + s * (bz - az)
            z0, z1 = zwall[e, 0], zwall[e, 1]
            if z <= z0 or z >= z1:
                return True
            if table[e, min(int(t * T), T - 1), min(max(int((z - z0) / (z1 - z0) * Z), 0), Z - 1)] > 0.0:
                return True
    return False


@njit(**_opts)
def room_image_taps(src, mute, seqs, edges, normal, table, zwall, first, zf, zc, rf, rc, lis, R, mode, d0, D,
                    near_k, bulk, c_sound, pts, delay, gain, Y, d_prev, g_prev, Y_prev):
    """Image sources of a set of rooms for sources src (n, 3) heard at lis. The rooms' walls are pooled: edges
    (E, 4) plan segments (x0, y0, x1, y1) with outward normals normal (E, 2), each between its room's floor and
    ceiling (zwall (E, 2)), with its amplitude reflection factor sampled along (T) and up (Z) it (table (E, T, Z):
    0 where it is open); room r's walls are edges[first[r]:first[r + 1]], its floor and ceiling at zf[r], zc[r]
    with factors rf[r], rc[r]. seqs (M, order): the reflector sequences (wall e < E; E + 2r room r's floor,
    E + 2r + 1 its ceiling; -1 pads). An image counts when the path traced back from the listener meets every
    reflector in order, inside its extent (a wall where it is solid, a floor or ceiling inside its room), and no
    leg meets a solid wall (:func:`_blocked`); its gain is the distance law x the reflectors' factors. A source in
    none of the rooms (in plan, and within 0.5 m of its floor and ceiling) or unheard (mute (n,)) has none. Writes
    delay (n, M) s, gain (n, M) and the N3D SH (n, M, 9) of the arrival direction in the head frame (R: world ->
    head). An image that has just appeared starts from its own delay and direction (d_prev, Y_prev set where g_prev
    is 0: it fades in without a sweep); one that has gone keeps its last delay and direction while it fades out.
    pts (order + 1, 3) float64 scratch."""
    n, M = delay.shape
    E = edges.shape[0]
    T, Z = table.shape[1], table.shape[2]
    order = seqs.shape[1]
    for i in range(n):
        here = False
        if not mute[i]:
            for r in range(len(zf)):
                if zf[r] - 0.5 <= src[i, 2] <= zc[r] + 0.5 and _inside(src[i, 0], src[i, 1], edges, first[r],
                                                                        first[r + 1]):
                    here = True
                    break
        for k in range(M):
            g = 0.0
            d = 0.0
            v0 = v1 = v2 = 0.0
            if here:
                # the images: pts[j] the source reflected by the first j reflectors
                pts[0, 0], pts[0, 1], pts[0, 2] = src[i, 0], src[i, 1], src[i, 2]
                m = 0
                while m < order and seqs[k, m] >= 0:
                    p = seqs[k, m]
                    x, y, z = pts[m, 0], pts[m, 1], pts[m, 2]
                    if p < E:
                        nx, ny = normal[p, 0], normal[p, 1]
                        h = (x - edges[p, 0]) * nx + (y - edges[p, 1]) * ny
                        pts[m + 1, 0], pts[m + 1, 1], pts[m + 1, 2] = x - 2 * h * nx, y - 2 * h * ny, z
                    elif (p - E) % 2 == 0:
                        pts[m + 1, 0], pts[m + 1, 1], pts[m + 1, 2] = x, y, 2 * zf[(p - E) // 2] - z
                    else:
                        pts[m + 1, 0], pts[m + 1, 1], pts[m + 1, 2] = x, y, 2 * zc[(p - E) // 2] - z
                    m += 1
                # trace back from the listener: towards image j, meet reflector j
                amp = 1.0
                px, py, pz = lis[0], lis[1], lis[2]
                prev_wall = -1
                for j in range(m, 0, -1):
                    p = seqs[k, j - 1]
                    ix, iy, iz = pts[j, 0], pts[j, 1], pts[j, 2]
                    # signed distances beyond the reflector (outward): the listener's side must be in front
                    rr = (p - E) // 2
                    if p < E:
                        nx, ny = normal[p, 0], normal[p, 1]
                        hp = (px - edges[p, 0]) * nx + (py - edges[p, 1]) * ny
                        hi_ = (ix - edges[p, 0]) * nx + (iy - edges[p, 1]) * ny
                    elif (p - E) % 2 == 0:
                        hp, hi_ = zf[rr] - pz, zf[rr] - iz
                    else:
                        hp, hi_ = pz - zc[rr], iz - zc[rr]
                    if not (hp < 0.0 < hi_):
                        amp = 0.0
                        break
                    s = hp / (hp - hi_)
                    qx, qy, qz = px + s * (ix - px), py + s * (iy - py), pz + s * (iz - pz)
                    wall = -1
                    if p < E:
                        ex, ey = edges[p, 2] - edges[p, 0], edges[p, 3] - edges[p, 1]
                        t = ((qx - edges[p, 0]) * ex + (qy - edges[p, 1]) * ey) / max(ex * ex + ey * ey, 1e-18)
                        z0, z1 = zwall[p, 0], zwall[p, 1]
                        if t < 0.0 or t > 1.0 or qz < z0 or qz > z1:
                            amp = 0.0
                            break
                        amp *= table[p, min(int(t * T), T - 1), min(max(int((qz - z0) / (z1 - z0) * Z), 0), Z - 1)]
                        wall = p
                    elif _inside(qx, qy, edges, first[rr], first[rr + 1]):
                        amp *= rf[rr] if (p - E) % 2 == 0 else rc[rr]
                    else:
                        amp = 0.0
                    if amp == 0.0 or _blocked(px, py, pz, qx, qy, qz, edges, table, zwall, prev_wall, wall):
                        amp = 0.0
                        break
                    px, py, pz, prev_wall = qx, qy, qz, wall
                if amp > 0.0 and _blocked(px, py, pz, src[i, 0], src[i, 1], src[i, 2], edges, table, zwall,
                                          prev_wall, -1):
                    amp = 0.0
                if amp > 0.0:
                    v0, v1, v2 = pts[m, 0] - lis[0], pts[m, 1] - lis[1], pts[m, 2] - lis[2]
                    d = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
                    g = distance_gain_1(d, mode, d0, D, near_k) * amp
                    if g < 1e-4:  # below -80 dB: left out
                        g = 0.0
            if g == 0.0:  # gone (or never there): hold the last delay and direction while the gain ramps out
                gain[i, k] = 0.0
                delay[i, k] = d_prev[i, k]
                for c in range(9):
                    Y[i, k, c] = Y_prev[i, k, c]
                continue
            gain[i, k] = g
            delay[i, k] = min(d, D) / c_sound + bulk
            _sh9(R, v0, v1, v2, d, Y[i, k])
            if g_prev[i, k] == 0.0:  # appearing: start where it is
                d_prev[i, k] = delay[i, k]
                for c in range(9):
                    Y_prev[i, k, c] = Y[i, k, c]
