"""Propagation paths: how a sound without line of sight reaches a listener (around corners, through doorways).

Baked once per scene (:func:`path_graph`, cached in memory by the static structure's hash and the doors):

* a horizontal slice of the static structure at ear height, rasterised on a grid (``cell``, default 0.1 m) by
  Embree rays along every row and column: a cell is blocked where a surface crosses it (walls of any thickness,
  zero-thickness panels, tall furniture; door leaves are dynamic and not in it). Free pockets too small to hold a
  person (the inside of a thick wall) are blocked too;
* the nodes of a visibility graph: the convex corners of the free space (a free cell whose diagonal neighbour is
  blocked while the two cells beside both are free: wall ends, door jambs, room corners that turn outward);
* its edges: node pairs in line of sight on the grid (exact cell traversal), weighted by length;
* the doors: each leaf, where it is now, is an obstacle (segment) that cuts the edges it crosses, with two more
  nodes by its free end, one on each side; the doorway (the closed leaf's segment) is a portal whose aperture
  scales the energy of paths through it;
* all-pairs shortest paths (Dijkstra), recomputed with the leaves' edges when a door moves (milliseconds for a
  home: 24 nodes in the default apartment).

At run time (:class:`Paths`), for each source and listener without line of sight on the slice: the nodes each
can see (cached per source and per listener until it moves), the shortest path S -> a ... b -> L over them, and
along it:

* its length (3-D: the height difference spread along the path), so the delay and the distance law follow it;
* the direction of its last bend b, which is where the listener hears it from;
* a diffraction loss per band at every bend, from the Fresnel number N = 2 delta f / c of that bend's detour
  delta (the path over the edge minus the straight line between its neighbours): 10 log10(1 + 20 N) dB (Maekawa's
  chart without its 5 dB step, so the level is continuous where line of sight is gained or lost: delta -> 0 there),
  at most 25 dB per bend;
* every door it passes through by the energy fraction of its aperture (a leaf opened by theta leaves a gap of
  2 w sin(theta / 2), at most the doorway's width w).

The renderer adds this path and the transmission through the walls along the straight line (the occlusion
subsystem) in energy and hears the sum from a virtual source blended between the two by their energies: from the
doorway when the path dominates, through the wall when the door is shut.
"""
from __future__ import annotations

import copy
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from sonicverse_core.acoustics.path_kernels import _crosses, combine_paths, grid_los, trace_paths, visible_nodes
from sonicverse_core.acoustics.state import PerSource
from sonicverse_core.scene.materials import BANDS

DIFFRACTION_MODELS = ("fresnel", "none")
DOOR_STATES = 16  # door states whose graph (and coupled rooms' balance, coupling.py) are kept
MAX_NODES = 800
MIN_POCKET = 0.2  # m: free regions whose widest point is narrower than this are inside walls, not rooms


def remember(kept: dict, key, value) -> None:
    """``kept[key] = value`` as the newest entry, the oldest dropped beyond ``DOOR_STATES``."""
    kept.pop(key, None)
    kept[key] = value
    while len(kept) > DOOR_STATES:
        kept.pop(next(iter(kept)))




@dataclass
class PathResult:
    """One source's path to a listener: ``length`` (2-D, m), its ``last`` and ``first`` bends (2,) and its
    ``amplitude`` (9,) per band (diffraction at every bend x the doorways' apertures)."""

    length: float
    last: np.ndarray
    first: np.ndarray
    amplitude: np.ndarray


def _segments_cross(p: np.ndarray, q: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(m,) do segments p[i] -> q[i] cross the segment a -> b (proper intersection)?"""
    d1 = (q[:, 0] - p[:, 0]) * (a[1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (a[0] - p[:, 0])
    d2 = (q[:, 0] - p[:, 0]) * (b[1] - p[:, 1]) - (q[:, 1] - p[:, 1]) * (b[0] - p[:, 0])
    d3 = (b[0] - a[0]) * (p[:, 1] - a[1]) - (b[1] - a[1]) * (p[:, 0] - a[0])
    d4 = (b[0] - a[0]) * (q[:, 1] - a[1]) - (b[1] - a[1]) * (q[:, 0] - a[0])
    return (d1 * d2 < 0) & (d3 * d4 < 0)


class PathGraph:
    """The baked slice, nodes, edges and shortest paths of a scene (see the module docstring)."""

    def __init__(self, scene, cell: float = 0.1, height: float = 1.5, caster=None):
        from sonicverse_core.geometry.raycast import SceneRayCaster

        self.scene, self.cell = scene, float(cell)
        caster = caster or SceneRayCaster(scene)
        lo, hi = scene.bounds[0, :2], scene.bounds[1, :2]
        c = self.cell
        self.origin = np.floor(lo / c) * c - c
        self.shape = (int(np.ceil((hi[1] - self.origin[1]) / c)) + 2, int(np.ceil((hi[0] - self.origin[0]) / c)) + 2)
        self.z = scene.floor_z + height
        self.blocked = self._slice(caster)
        self.static_nodes = self._corners()
        self.doors = [d for d in scene.doors]
        self.door_segments = np.array([self._doorway(d) for d in self.doors], float).reshape(-1, 4)
        self.nodes = self.static_nodes
        self._edges()
        self._leaf_key = None
        self._states: dict = {}  # leaf positions -> the graph with them (the last DOOR_STATES met)
        # two nodes by every door leaf's free end, one on each side (moved with the leaf by refresh)
        self.nodes = np.vstack([self.static_nodes, np.zeros((2 * len(self.doors), 2))])
        self.refresh()

    # --- bake ---------------------------------------------------------------------------------------------------
    def _slice(self, caster) -> np.ndarray:
        from scipy import ndimage

        ny, nx = self.shape
        c, o = self.cell, self.origin
        blocked = np.zeros((ny, nx), bool)
        ys = o[1] + (np.arange(ny) + 0.5) * c
        xs = o[0] + (np.arange(nx) + 0.5) * c
        x_end, y_end = o[0] + nx * c, o[1] + ny * c
        rows = np.c_[np.full(ny, o[0]), ys, np.full(ny, self.z)], np.c_[np.full(ny, x_end), ys, np.full(ny, self.z)]
        cols = np.c_[xs, np.full(nx, o[1]), np.full(nx, self.z)], np.c_[xs, np.full(nx, y_end), np.full(nx, self.z)]
        mesh = scene_mesh = self.scene.static_mesh()
        tri = scene_mesh.vertices[mesh.faces]
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        for (a, b), along in ((rows, 0), (cols, 1)):
            cr = caster.crossings(a, b, include_dynamic=False, max_hits=4096)
            if len(cr.ray) == 0:
                continue
            # cell units along the ray; +0.01 cell: a surface on a cell boundary falls in the same cell on every
            # row (Embree's float32 distances would otherwise scatter it over both, making a jagged wall)
            u = (a[cr.ray, along] + cr.distance - o[along]) / c + 0.01
            k = np.clip(u.astype(int), 0, (nx, ny)[along] - 1)
            i, j = (cr.ray, k) if along == 0 else (k, cr.ray)
            blocked[i, j] = True
            # inside closed solids: from a face the ray enters (against its outward normal) to the next face of
            # the same part, which it leaves (a panel or an inward-facing room shell fills nothing)
            enter = normals[cr.face, along] < 0
            order = np.lexsort((cr.distance, cr.part, cr.ray))
            r, p, e, kk = cr.ray[order], cr.part[order], enter[order], k[order]
            pair = (r[:-1] == r[1:]) & (p[:-1] == p[1:]) & e[:-1] & ~e[1:]
            for q in np.flatnonzero(pair):
                if along == 0:
                    blocked[r[q], kk[q]:kk[q + 1] + 1] = True
                else:
                    blocked[kk[q]:kk[q + 1] + 1, r[q]] = True
        free = ~blocked
        labels, n = ndimage.label(free)  # 4-connected
        if n:
            edt = ndimage.distance_transform_edt(free) * c
            widest = ndimage.maximum(edt, labels, np.arange(1, n + 1))
            border = np.unique(np.r_[labels[0], labels[-1], labels[:, 0], labels[:, -1]])
            keep = np.asarray(widest) >= MIN_POCKET
            inside = keep.copy()
            inside[border[border > 0] - 1] = False
            if inside.any():  # an enclosure: the outside of the building is not part of it
                keep = inside
            blocked = ~np.r_[False, keep][labels]
        return blocked

    def _corners(self) -> np.ndarray:
        b = self.blocked
        free = ~b
        pad = np.pad(b, 1, constant_values=True)
        corner = np.zeros_like(b)
        ny, nx = b.shape
        for di in (-1, 1):
            for dj in (-1, 1):
                diag = pad[1 + di:1 + di + ny, 1 + dj:1 + dj + nx]
                side_i = pad[1 + di:1 + di + ny, 1:1 + nx]
                side_j = pad[1:1 + ny, 1 + dj:1 + dj + nx]
                corner |= free & diag & ~side_i & ~side_j
        ij = np.argwhere(corner)
        if len(ij) > MAX_NODES:  # thin out (cluttered mesh scenes): keep a node every few cells
            step = int(np.ceil(np.sqrt(len(ij) / MAX_NODES)))
            _, keep = np.unique(ij // (2 * step), axis=0, return_index=True)
            ij = ij[np.sort(keep)][:MAX_NODES]
        return self.origin + (ij[:, ::-1] + 0.5) * self.cell

    @staticmethod
    def _doorway(door) -> tuple:
        a = np.radians(door.closed_yaw)
        h = np.asarray(door.hinge, float)
        return (*h, *(h + door.width * np.array([np.cos(a), np.sin(a)])))

    def _edges(self) -> None:
        N = len(self.nodes)
        vis = np.zeros(N, bool)
        none = np.zeros((0, 4))
        rows, cols = [], []
        for k in range(N):
            visible_nodes(self.blocked, self.origin, self.cell, self.nodes[k], self.nodes[k + 1:], none,
                          np.zeros(0, bool), vis[: N - k - 1])
            m = np.flatnonzero(vis[: N - k - 1]) + k + 1
            rows.append(np.full(len(m), k))
            cols.append(m)
        self.edge_i = np.concatenate(rows) if rows else np.zeros(0, int)
        self.edge_j = np.concatenate(cols) if cols else np.zeros(0, int)
        e = self.nodes[self.edge_j] - self.nodes[self.edge_i]
        self.edge_len = np.hypot(e[:, 0], e[:, 1])

    # --- doors --------------------------------------------------------------------------------------------------
    def apertures(self) -> np.ndarray:
        """Energy fraction of every doorway left open by its leaf: 2 sin(theta / 2), at most 1 (theta = 90 deg x the
        open fraction)."""
        return np.array([min(1.0, 2 * np.sin(np.radians(45.0 * d.open_fraction))) for d in self.doors])

    def leaf_segments(self) -> np.ndarray:
        """(d, 4) every door leaf where it is now, hinge to free end (a closed leaf is its doorway)."""
        out = np.zeros((len(self.doors), 4))
        for k, d in enumerate(self.doors):
            a = np.radians(d.closed_yaw + d.swing * 90.0 * d.open_fraction)
            h = np.asarray(d.hinge, float)
            out[k] = (*h, *(h + d.width * np.array([np.cos(a), np.sin(a)])))
        return out

    def refresh(self) -> bool:
        """Follow the doors: apertures, the leaves as obstacles, the nodes by their free ends, the edges they cut or
        add, and the shortest paths, when a leaf moved since the last call; True when something changed. The graphs of
        the last ``DOOR_STATES`` leaf positions are kept: a door shut and opened again costs a look-up."""
        self.aperture = self.apertures()
        leaves = self.leaf_segments()
        key = np.round(leaves, 4).tobytes()
        if key == self._leaf_key:
            return False
        self._leaf_key = key
        ns = len(self.static_nodes)
        seen = self._states.get(key)
        if seen is not None:  # a door state met before (a door shut and opened again): its graph, kept
            self.leaves, self.blocking, self.node_ok, tips, self.dist, self.pred = seen
            self.nodes[ns:] = tips
        else:
            self._compute(leaves)
            seen = (self.leaves, self.blocking, self.node_ok, self.nodes[ns:].copy(), self.dist, self.pred)
        remember(self._states, key, seen)
        return True

    def _compute(self, leaves: np.ndarray) -> None:
        """:meth:`refresh`'s work for door leaves where they are now: the leaves as obstacles, the nodes by their
        free ends, the edges they cut or add, the shortest paths."""
        from scipy.sparse import csr_matrix
        from scipy.sparse.csgraph import shortest_path as sp

        self.leaves = leaves
        self.blocking = np.ones(len(leaves), bool)
        ns, D = len(self.static_nodes), len(self.doors)
        self.node_ok = np.ones(ns + 2 * D, bool)
        rows, cols, lens = [self.edge_i], [self.edge_j], [self.edge_len]
        if D:
            p, q = self.static_nodes[self.edge_i], self.static_nodes[self.edge_j]
            cut = np.zeros(len(self.edge_i), bool)
            for x0, y0, x1, y1 in leaves:
                cut |= _segments_cross(p, q, np.array([x0, y0]), np.array([x1, y1]))
            rows, cols, lens = [self.edge_i[~cut]], [self.edge_j[~cut]], [self.edge_len[~cut]]
            vis = np.zeros(ns + 2 * D, bool)
            for k, (x0, y0, x1, y1) in enumerate(leaves):
                v = np.array([x1 - x0, y1 - y0]) / max(np.hypot(x1 - x0, y1 - y0), 1e-9)
                nrm = np.array([-v[1], v[0]])
                for side, sgn in enumerate((1.0, -1.0)):
                    t = ns + 2 * k + side
                    self.nodes[t] = np.array([x1, y1]) + 0.5 * self.cell * v + sgn * 0.7 * self.cell * nrm
                    gi, gj = ((self.nodes[t] - self.origin) / self.cell)[::-1].astype(int)
                    inside = 0 <= gi < self.shape[0] and 0 <= gj < self.shape[1]
                    self.node_ok[t] = inside and not self.blocked[gi, gj]
            for t in range(ns, ns + 2 * D):
                if not self.node_ok[t]:
                    continue
                visible_nodes(self.blocked, self.origin, self.cell, self.nodes[t], self.nodes, leaves,
                              self.blocking, vis)
                vis &= self.node_ok
                vis[: t + 1] &= np.arange(t + 1) < ns  # each tip-tip pair once
                m = np.flatnonzero(vis)
                m = m[m != t]
                rows.append(np.full(len(m), t))
                cols.append(m)
                lens.append(np.hypot(*(self.nodes[m] - self.nodes[t]).T))
        N = len(self.nodes)
        if N == 0:
            self.dist, self.pred = np.zeros((0, 0)), np.zeros((0, 0), np.int32)
            return
        i, j, w = np.concatenate(rows), np.concatenate(cols), np.concatenate(lens)
        m = csr_matrix((w + 1e-9, (i, j)), shape=(N, N))
        dist, pred = sp(m, method="D", directed=False, return_predecessors=True)
        self.dist, self.pred = dist, pred.astype(np.int32)

    # --- queries ------------------------------------------------------------------------------------------------
    def grid_point(self, p) -> tuple[float, float]:
        return (p[0] - self.origin[0]) / self.cell, (p[1] - self.origin[1]) / self.cell

    def line_of_sight(self, a, b) -> bool:
        """Open line of sight on the slice between 2-D points (walls block; furniture under ear height does not),
        past every door leaf."""
        if not grid_los(self.blocked, *self.grid_point(a), *self.grid_point(b)):
            return False
        return not any(_crosses(a[0], a[1], b[0], b[1], *s) for s in self.leaves)

    def visible(self, p) -> np.ndarray:
        out = np.zeros(len(self.nodes), bool)
        if len(self.nodes):
            visible_nodes(self.blocked, self.origin, self.cell, np.asarray(p[:2], float), self.nodes,
                          self.leaves, self.blocking, out)
            out &= self.node_ok
        return out

    def path(self, s, lis, model: str = "fresnel") -> PathResult | None:
        """The path the renderer takes from 2-D point s to 2-D point lis (the same kernel): None when they see each
        other on the slice or no open path joins them."""
        if len(self.nodes) == 0:
            return None
        pos = np.array([[s[0], s[1], 0.0]])
        on, length = np.zeros(1, bool), np.zeros(1)
        last, first, amp = np.zeros((1, 2)), np.zeros((1, 2)), np.zeros((1, len(BANDS)))
        trace_paths(np.zeros(1, np.int64), pos, np.array([lis[0], lis[1], 0.0]), self.visible(s)[None],
                    self.visible(lis), self.blocked, self.origin, self.cell, self.nodes, self.dist, self.pred,
                    self.leaves, self.door_segments, self.aperture, BANDS, 343.0, model != "none", on, length, last,
                    first, amp)
        return PathResult(float(length[0]), last[0], first[0], amp[0]) if on[0] else None


_CACHE: OrderedDict = OrderedDict()


def path_graph(scene, cell: float = 0.1, height: float = 1.5, caster=None) -> PathGraph:
    """The scene's path graph, baked once per static structure, door layout, cell and height (8 kept)."""
    doors = tuple((d.name, tuple(np.round(d.hinge, 4)), round(d.closed_yaw, 3), round(d.width, 4))
                  for d in scene.doors)
    key = (scene.static_hash(), doors, cell, height)
    g = _CACHE.get(key)
    if g is None:
        g = PathGraph(scene, cell, height, caster)
        _CACHE[key] = g
        while len(_CACHE) > 8:
            _CACHE.popitem(last=False)
    _CACHE.move_to_end(key)
    if g.scene is not scene:  # the same structure in another scene object: its own doors
        g = copy.copy(g)
        g.scene, g.doors, g._leaf_key, g.nodes = scene, list(scene.doors), None, g.nodes.copy()
        g.refresh()
    return g


class PathsState(PerSource):
    """A listener's paths: per source whether it has one (``on``), its length, its last and first bends, its
    per-band amplitude, the segment it was traced for (``seg``, NaN: never) and how far that moved, the emitter it
    makes (``eff``, ``fwd``, ``rel``) and the per-band ``target`` it hands on; the graph nodes the listener sees
    (``vis_l``, from where: ``vis_l_at``) and the scene version they were found in."""

    __slots__ = ("on", "length", "last", "first", "amp", "seg", "rel", "target", "eff", "fwd", "moved", "vis_l",
                 "vis_l_at", "version")
    ROWS = (("on", (), bool, False), ("length", (), np.float64, 0.0), ("last", (2,), np.float64, 0.0),
            ("first", (2,), np.float64, 0.0), ("amp", (len(BANDS),), np.float64, 0.0),
            ("seg", (6,), np.float64, np.nan), ("rel", (3,), np.float64, 0.0),
            ("target", (len(BANDS),), np.float64, 1.0), ("eff", (3,), np.float64, 0.0),
            ("fwd", (3,), np.float64, 0.0), ("moved", (), np.float64, 0.0))

    def __init__(self, cap: int, nodes: int):
        super().__init__(cap)
        self.vis_l = np.zeros(nodes, bool)
        self.vis_l_at = np.full(3, np.nan)
        self.version = None


class Paths:
    """The renderer's propagation-path subsystem (:class:`~sonicverse_core.acoustics.state.Subsystem`): the scene's
    :class:`PathGraph`, the nodes each source sees (shared by listeners, kept until the source moves), and per
    listener (:class:`PathsState`) each source's path, recomputed when an end moved more than ``tolerance`` or a
    door moved, at most ``budget`` a block.

    :meth:`apply` turns a block's straight-line transmission (the occlusion subsystem's per-band target) into what
    the direct renderer plays: per source, the path and the transmission added in energy and heard from a virtual
    source blended between the path's last bend and the source by their energies, at the blended length; the
    source's forward turned so that its directivity acts on the path's first leg. ``rolloff``: the renderer's
    distance-law parameters (mode, d0, max distance, near-field factor)."""

    name = "paths"

    def __init__(self, graph: PathGraph, diffraction: str = "fresnel", tolerance: float = 0.02, budget: int = 64,
                 rolloff: tuple = (0, 1.0, 500.0, 0.0)):
        self.graph, self.tolerance, self.budget = graph, tolerance, budget
        self.bend_loss = diffraction != "none"
        self.rolloff = rolloff
        self._version = None
        self._src_at = np.zeros((0, 3))
        self._vis = np.zeros((0, len(graph.nodes)), bool)
        self.stats = {"paths": 0, "path_queries": 0}

    # --- the subsystem protocol ----------------------------------------------------------------------------------
    def state(self, cap: int) -> PathsState:
        return PathsState(cap, len(self.graph.nodes))

    def grow(self, st: PathsState | None, cap: int) -> None:
        """Room for ``cap`` sources (None: the nodes the sources see; or one listener's state)."""
        from sonicverse_core.acoustics.sources import grown as _grown

        if st is None:
            self._src_at = _grown(self._src_at, (cap, 3), np.float64, np.nan)
            self._vis = _grown(self._vis, (cap, len(self.graph.nodes)), bool)
            return
        st.grow(cap)

    def max_delay(self) -> float:
        return 0.0  # a path's emitter is read by the direct sound, within its maximum distance

    def render(self, st: PathsState, ls, lis, out) -> None:
        """The block's emitters and targets for the stages after it (``ls.pos``, ``ls.fwd``, ``ls.target``)."""
        self.update(st, ls.pos, lis.position)
        ls.target, ls.pos, ls.fwd = self.apply(st, ls.pos, ls.fwd, lis.position, ls.target, self.rolloff,
                                               ls.smoothing, ls.fresh[:ls.n])

    def reset(self, st: PathsState) -> None:
        pass

    def update(self, st: PathsState, pos: np.ndarray, lis: np.ndarray) -> None:
        from sonicverse_core.acoustics.kernels import count_over, farther, segment_motion

        g, n = self.graph, len(pos)
        version = g.scene.dynamic_version
        if version != self._version:  # a door moved: new apertures, maybe new shortest paths; recompute everything
            g.refresh()
            self._version = version
            self._src_at[:] = np.nan
        if st.version != version:
            st.version = version
            st.seg[:] = np.nan
            st.vis_l_at[:] = np.nan
        if farther(st.vis_l_at, lis, self.tolerance):  # NaN: never computed
            g_vis = st.vis_l
            if len(g.nodes):
                visible_nodes(g.blocked, g.origin, g.cell, lis[:2].astype(np.float64), g.nodes, g.leaves,
                              g.blocking, g_vis)
                g_vis &= g.node_ok
            st.vis_l_at[:] = lis
        moved = st.moved[:n]
        segment_motion(pos, lis, st.seg[:n], moved)
        if not count_over(moved, self.tolerance):  # the steady state: nothing to trace, nothing allocated
            return
        todo = np.flatnonzero(moved > self.tolerance)
        if len(todo) > self.budget:
            todo = todo[np.argsort(-moved[todo], kind="stable")[: self.budget]]
        if len(todo) == 0:
            return
        stale = todo[~(np.max(np.abs(self._src_at[todo] - pos[todo]), axis=1) <= self.tolerance)]
        for i in stale:  # the nodes a source sees, kept while it stays within the tolerance
            if len(g.nodes):
                visible_nodes(g.blocked, g.origin, g.cell, pos[i, :2].astype(np.float64), g.nodes, g.leaves,
                              g.blocking, self._vis[i])
                self._vis[i] &= g.node_ok
            self._src_at[i] = pos[i]
        trace_paths(todo.astype(np.int64), pos, lis.astype(np.float64), self._vis, st.vis_l, g.blocked, g.origin,
                    g.cell, g.nodes, g.dist, g.pred, g.leaves, g.door_segments, g.aperture, BANDS, 343.0,
                    self.bend_loss, st.on, st.length, st.last, st.first, st.amp)
        st.seg[todo] = np.concatenate([pos[todo], np.broadcast_to(lis, (len(todo), 3))], axis=1)
        self.stats["path_queries"] += len(todo)

    def apply(self, st: PathsState, pos: np.ndarray, fwd: np.ndarray, lis: np.ndarray, transmission: np.ndarray,
              rolloff: tuple, smoothing: float, fresh: np.ndarray):
        """(per-band target (n, 9), emitter positions (n, 3), forwards (n, 3)) for this block, in the listener's
        buffers (valid until its next block)."""
        n = len(pos)
        target, eff, f = st.target[:n], st.eff[:n], st.fwd[:n]
        np.copyto(target, transmission)
        np.copyto(eff, pos)
        np.copyto(f, fwd)
        self.stats["paths"] = combine_paths(st.on[:n], pos, fwd, lis, transmission,
                                            st.length[:n], st.last[:n], st.first[:n],
                                            st.amp[:n], st.rel[:n], fresh, float(smoothing or 0.0),
                                            *rolloff, target, eff, f)
        return target, eff, f
