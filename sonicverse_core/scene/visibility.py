"""Which rooms can be seen from which: the potentially visible set (PVS) a renderer loads, and the faces of each room.

A viewer in room A can see room B when a sight line joins them that crosses no wall. Sight lines are sampled,
once per scene: random pairs of points on a grid inside the two rooms at three heights, and lines through a
random point of a doorway of each (any sight line between rooms whose only openings are doors passes through one
of each, so a view down a corridor through two doors is not missed); one batched Embree query over the static
structure. Furniture does not hide a room and neither does a closed door (the gaps round a closed leaf show
slivers of the room behind it; measured by ``sonicverse bench vr``, which counts background pixels where the whole
scene shows a surface). Two rooms that share a door always see each other. A viewer outside every room sees
everything.

The static structure is split by room: a face belongs to the room whose footprint, grown by ``margin`` (a wall's
thickness and more), holds all its vertices; a face two rooms hold (a wall between them) or none (a floor or an
outer wall running along several rooms) belongs to no room and is always drawn, so nothing is drawn twice.
"""
from __future__ import annotations

import numpy as np

from sonicverse_core.scene.model import Scene, points_in_polygon


def boundary_distance(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(n,) distance of points (n, 2) to the boundary of the polygon (k, 2)."""
    a, b = poly, np.roll(poly, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("nkj,kj->nk", pts[:, None] - a[None], ab) / np.maximum((ab ** 2).sum(1), 1e-12), 0, 1)
    return np.linalg.norm(pts[:, None] - (a[None] + t[..., None] * ab[None]), axis=2).min(1)


def near_polygon(pts: np.ndarray, poly: np.ndarray, margin: float) -> np.ndarray:
    """Bool (n,): points (n, 2) inside the polygon (k, 2) or within ``margin`` of its boundary."""
    return points_in_polygon(pts, poly) | (boundary_distance(pts, poly) <= margin)


def room_faces(scene: Scene, margin: float = 0.3) -> dict[str | None, np.ndarray]:
    """Static face indices per room name; None: the faces no single room holds (always drawn)."""
    sm = scene.static_mesh()
    if not len(sm) or not scene.rooms:
        return {None: np.arange(len(sm))}
    v = sm.vertices[sm.faces][..., :2].reshape(-1, 2)  # (3f, 2)
    held = np.stack([near_polygon(v, r.footprint, margin).reshape(-1, 3).all(1) for r in scene.rooms])
    one = held.sum(0) == 1
    out: dict[str | None, np.ndarray] = {r.name: np.flatnonzero(one & held[k]) for k, r in enumerate(scene.rooms)}
    out[None] = np.flatnonzero(~one)
    return out


def object_room(scene: Scene, obj) -> str | None:
    """The room wholly holding an object (its box's corners); None for a door (it is seen from both of its rooms)
    and for an object no single room holds: those are always drawn."""
    from sonicverse_core.scene.model import Door

    if isinstance(obj, Door):
        return None
    lo, hi = obj.world_bounds()
    corners = np.array([[lo[0], lo[1]], [lo[0], hi[1]], [hi[0], lo[1]], [hi[0], hi[1]]])
    for r in scene.rooms:
        if r.contains(corners).all():
            return r.name
    return None


class RoomVisibility:
    """Potentially visible rooms per room. ``visible_from(xy)``: the room names a viewer at ``xy`` may see (None:
    everything, the viewer is in no room)."""

    def __init__(self, scene: Scene, spacing: float = 0.5, heights=(0.5, 1.1, 1.7), pairs: int = 1000,
                 portal_lines: int = 200, seed: int = 0):
        from sonicverse_core.geometry.raycast import SceneRayCaster

        self.scene = scene
        self.names = [r.name for r in scene.rooms]
        rng = np.random.default_rng(seed)
        points = []
        for r in scene.rooms:
            lo, hi = r.footprint.min(0), r.footprint.max(0)
            gx, gy = np.meshgrid(np.arange(lo[0] + spacing / 2, hi[0], spacing),
                                 np.arange(lo[1] + spacing / 2, hi[1], spacing))
            xy = np.stack([gx.ravel(), gy.ravel()], 1)
            xy = xy[points_in_polygon(xy, r.footprint) & (boundary_distance(xy, r.footprint) > 0.15)]  # not in a wall
            if len(xy) == 0:
                xy = r.footprint.mean(0, keepdims=True)
            points.append(np.concatenate([np.c_[xy, np.full(len(xy), r.z_floor + h)] for h in heights]))
        doorways = [self._doorways(r) for r in scene.rooms]
        # sampled sight lines: random point pairs of two rooms, and lines through a doorway of each (any sight line
        # between rooms whose only openings are doors passes through one of each: chains of doors are not missed)
        a, b, pair, pair_ij = [], [], [], []
        for i in range(len(self.names)):
            for j in range(i + 1, len(self.names)):
                ka, kb = rng.integers(0, len(points[i]), pairs), rng.integers(0, len(points[j]), pairs)
                lines = [(points[i][ka], points[j][kb])]
                lines += [self._through(da, db, scene.rooms[i], scene.rooms[j], rng, portal_lines)
                          for da in doorways[i] for db in doorways[j]]
                for la, lb in lines:
                    a.append(la)
                    b.append(lb)
                    pair.append(np.full(len(la), len(pair_ij)))
                pair_ij.append((i, j))
        n = len(self.names)
        see = np.eye(n, dtype=bool)
        if a:
            # only walls hide a room: furniture never hides a whole room, and a closed door leaves gaps round its
            # leaf (measured: a closed leaf still shows slivers of the room behind it), so the sets never change
            a, b, pair = np.concatenate(a), np.concatenate(b), np.concatenate(pair)
            clear = np.ones(len(a), bool)
            clear[SceneRayCaster(scene).crossings(a, b, include_dynamic=False).ray] = False
            for p in np.unique(pair[clear]):
                i, j = pair_ij[p]
                see[i, j] = see[j, i] = True
        idx = {name: k for k, name in enumerate(self.names)}
        for d in scene.doors:  # rooms that share a door see each other, whatever the samples say
            if len(d.rooms) == 2 and all(r in idx for r in d.rooms):
                see[idx[d.rooms[0]], idx[d.rooms[1]]] = see[idx[d.rooms[1]], idx[d.rooms[0]]] = True
        self.sets = {self.names[i]: frozenset(self.names[j] for j in np.flatnonzero(see[i])) for i in range(n)}
        self.sight_lines = len(a)

    def _doorways(self, room) -> list:
        """(start (2,), end (2,), z0, z1) of the openings of the doors of ``room``."""
        out = []
        for d in self.scene.doors:
            if room.name in d.rooms:
                u = np.array([np.cos(np.radians(d.closed_yaw)), np.sin(np.radians(d.closed_yaw))])
                h = np.asarray(d.hinge, float)
                top = d.world_bounds(d.pose)[1][2]
                out.append((h, h + d.width * u, self.scene.floor_z + 0.1, max(top, self.scene.floor_z + 1.9)))
        return out

    @staticmethod
    def _through(da, db, ra, rb, rng, n: int):
        """n sight lines through random points of two doorways, each reaching 0.3 m into its room (lines whose
        ends fall outside the rooms are dropped)."""
        pa = np.c_[da[0] + rng.uniform(0.05, 0.95, (n, 1)) * (da[1] - da[0]), rng.uniform(da[2], da[3], n)]
        pb = np.c_[db[0] + rng.uniform(0.05, 0.95, (n, 1)) * (db[1] - db[0]), rng.uniform(db[2], db[3], n)]
        d = pb - pa
        e = 0.3 * d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
        for sign in (1, -1):  # the line may leave A's doorway either way: keep the ends that lie in A and in B
            a, b = pa - sign * e, pb + sign * e
            ok = ra.contains(a[:, :2]) & rb.contains(b[:, :2])
            if ok.any():
                return a[ok], b[ok]
        return np.zeros((0, 3)), np.zeros((0, 3))

    def visible_from(self, xy) -> frozenset | None:
        r = self.scene.room_at(np.asarray(xy, float)[:2])
        return None if r is None else self.sets[r.name]
