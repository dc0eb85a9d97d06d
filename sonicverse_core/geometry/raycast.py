"""Ray casting over scene triangles: Embree (embreex) for speed, trimesh's pure-numpy caster as the reference.

Both backends share one API and a test checks that they agree. Embree works in float32: hit distances agree with
the float64 reference to about 1e-5 relative.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sonicverse_core.errors import ConfigError
from sonicverse_core.scene.model import Scene, SceneMesh

BACKENDS = ("embree", "numpy")
#: how far past a hit the next query starts when walking along a segment (m)
STEP_EPS = 1e-4


@dataclass(frozen=True)
class Hits:
    """First hits of n rays. distance : (n,) float (inf: no hit); face, part, material : (n,) int (-1: no hit);
    normal : (n, 3) unit face normal (zeros: no hit)."""

    distance: np.ndarray
    face: np.ndarray
    part: np.ndarray
    material: np.ndarray
    normal: np.ndarray

    @property
    def hit(self) -> np.ndarray:
        return self.face >= 0

    def nearer(self, other: "Hits") -> "Hits":
        """Per ray, the nearer of these hits and ``other``'s (these where they tie)."""
        c = other.distance < self.distance
        return Hits(np.where(c, other.distance, self.distance), np.where(c, other.face, self.face),
                    np.where(c, other.part, self.part), np.where(c, other.material, self.material),
                    np.where(c[:, None], other.normal, self.normal))


@dataclass(frozen=True)
class Crossings:
    """Every surface crossed by segments, flat: ray, distance, part, material : (k,) arrays; dynamic : (k,) bool;
    face : (k,) the face crossed (static faces first, then the dynamic mesh's). A part crossed several times by one
    segment (both faces of a wall) appears once per face."""

    ray: np.ndarray
    distance: np.ndarray
    part: np.ndarray
    material: np.ndarray
    dynamic: np.ndarray
    face: np.ndarray


def _as_rays(origins, directions):
    o = np.atleast_2d(np.asarray(origins, dtype=np.float64))
    d = np.atleast_2d(np.asarray(directions, dtype=np.float64))
    if o.shape != d.shape or o.shape[-1] != 3:
        raise ConfigError(f"origins and directions must both be (n, 3), got {o.shape} and {d.shape}")
    if not (np.all(np.isfinite(o)) and np.all(np.isfinite(d))):
        raise ConfigError("ray origins and directions must be finite")
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    if np.any(norm == 0):
        raise ConfigError("ray directions must be non-zero")
    return o, d / norm


class RayCaster:
    """First-hit ray casting over one :class:`SceneMesh`."""

    def __init__(self, mesh: SceneMesh, backend: str = "embree"):
        if backend not in BACKENDS:
            raise ConfigError(f"unknown ray backend '{backend}'; use one of {', '.join(BACKENDS)}")
        self.mesh = mesh
        self.backend = backend
        tri = mesh.vertices[mesh.faces] if len(mesh) else np.zeros((0, 3, 3))
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) if len(mesh) else np.zeros((0, 3))
        ln = np.linalg.norm(n, axis=1, keepdims=True)
        self.normals = np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)
        self._impl = None
        if len(mesh) == 0:
            return
        if backend == "embree":
            from embreex import rtcore_scene as rtcs
            from embreex.mesh_construction import TriangleMesh

            self._impl = rtcs.EmbreeScene()
            TriangleMesh(self._impl, tri.astype(np.float32))
        else:
            import trimesh
            from trimesh.ray.ray_triangle import RayMeshIntersector

            self._impl = RayMeshIntersector(trimesh.Trimesh(mesh.vertices, mesh.faces, process=False))

    @property
    def empty(self) -> bool:
        return self._impl is None

    def faces(self, o: np.ndarray, d: np.ndarray, maxd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(face (n,) int, -1: no hit; distance (n,)) of the first hit of rays with finite origins ``o`` and unit
        directions ``d`` within ``maxd`` (n,): no checks, for inner loops (the mesh must not be empty)."""
        if self.backend == "embree":
            res = self._impl.run(o.astype(np.float32), d.astype(np.float32),
                                 dists=np.minimum(maxd, 3.0e38).astype(np.float32), output=1)
            return res["primID"].astype(np.int64), res["tfar"].astype(np.float64)
        h = self.first_hit(o, d, maxd)
        return h.face, h.distance

    def first_hit(self, origins, directions, max_distance=np.inf) -> Hits:
        """First surface hit by each ray (directions are normalised) within ``max_distance`` (scalar or (n,))."""
        o, d = _as_rays(origins, directions)
        n = len(o)
        maxd = np.broadcast_to(np.asarray(max_distance, dtype=np.float64), (n,))
        face = np.full(n, -1, dtype=np.int64)
        dist = np.full(n, np.inf)
        if self._impl is not None and n:
            if self.backend == "embree":
                lim = np.minimum(maxd, 3.0e38).astype(np.float32)
                res = self._impl.run(o.astype(np.float32), d.astype(np.float32), dists=lim, output=1)
                ok = res["primID"] >= 0
                face[ok] = res["primID"][ok]
                dist[ok] = res["tfar"][ok]
            else:
                loc, iray, itri = self._impl.intersects_location(o, d, multiple_hits=False)
                if len(iray):
                    t = np.einsum("ij,ij->i", loc - o[iray], d[iray])
                    keep = (t >= 0) & (t <= maxd[iray])
                    face[iray[keep]] = itri[keep]
                    dist[iray[keep]] = t[keep]
        hit = face >= 0
        part = np.where(hit, self.mesh.face_part[np.maximum(face, 0)] if len(self.mesh) else -1, -1)
        mat = np.where(hit, self.mesh.face_material[np.maximum(face, 0)] if len(self.mesh) else -1, -1)
        normal = np.zeros((n, 3))
        normal[hit] = self.normals[face[hit]]
        return Hits(dist, face, part, mat, normal)


class DynamicCaster:
    """The scene's objects where they are now, cast as two groups: the doors and every object that has moved since
    the caster was made (``movers``), and the rest (``still``). Each group is its own :class:`RayCaster`; a door that
    opens or an object carried rebuilds only the movers' (a few dozen triangles: 0.5 ms for the apartment's three
    doors, where the whole dynamic mesh, 3,128 triangles, took 8-10 ms in embreex's mesh construction: a dropout in
    a live stream each time a door moved; README, "A door's move in a live stream"). An object moved for the first time joins the movers, and the still group
    is built once more without it. Faces, parts and materials are those of the scene's ``dynamic_mesh`` (``mesh``),
    whichever group hit them: the same answers as one caster over the whole mesh (tested)."""

    def __init__(self, scene: Scene, backend: str, proxies: bool):
        self.scene, self.backend, self.proxies = scene, backend, proxies
        self._version = None
        self._names: tuple = ()
        self._poses: list = []  # per object, its pose (bytes) when its group was last built
        self.movers: set[str] = set()
        self._groups: dict[str, tuple] = {}  # "still" | "movers" -> (RayCaster, face map into ``mesh``)
        # how often each group's caster was built (a caller that keeps one group's hits knows when they went stale)
        self.builds = {"still": 0, "movers": 0}
        self.mesh = None
        self.sync()

    def sync(self) -> "DynamicCaster":
        """Follow the scene: rebuild the groups whose objects moved since the last call (nothing when its
        ``dynamic_version`` is unchanged)."""
        sc = self.scene
        if self._version == sc.dynamic_version:
            return self
        self._version = sc.dynamic_version
        self.mesh = sc.dynamic_mesh(self.proxies)
        objs = sc.objects
        names = tuple(o.name for o in objs)
        poses = [o.pose.tobytes() for o in objs]
        from sonicverse_core.scene.model import Door

        if names != self._names:  # new objects (or a new scene): everything again
            self._names, self._poses = names, poses
            self.movers = {o.name for o in objs if isinstance(o, Door)}
            self._build("still")
            self._build("movers")
            return self
        moved = {n for n, a, b in zip(names, self._poses, poses) if a != b}
        self._poses = poses
        if moved - self.movers:  # first moves: they join the movers, the still group is built without them
            self.movers |= moved
            self._build("still")
            self._build("movers")
        elif moved:
            self._build("movers")
        return self  # touched without a pose change: the groups' faces are those of the new mesh

    def _sub(self, fmap: np.ndarray) -> SceneMesh:
        m = self.mesh
        return SceneMesh(m.vertices, m.faces[fmap], m.face_material[fmap], m.face_part[fmap], m.part_names)

    def _build(self, group: str) -> None:
        m = self.mesh
        mover = np.array([n in self.movers for n in self._names], bool)
        pick = mover if group == "movers" else ~mover
        fmap = np.flatnonzero(pick[m.face_part]) if len(m) else np.zeros(0, np.int64)
        self._groups[group] = (RayCaster(self._sub(fmap), self.backend) if len(fmap) else None, fmap)
        self.builds[group] += 1

    @property
    def empty(self) -> bool:
        return all(c is None for c, _ in self._groups.values())

    def faces(self, o: np.ndarray, d: np.ndarray, maxd: np.ndarray,
              groups=("still", "movers")) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`RayCaster.faces`, the faces indexing ``mesh``: the nearest hit of ``groups``."""
        face = np.full(len(o), -1, np.int64)
        dist = np.full(len(o), np.inf)
        for caster, fmap in (self._groups[g] for g in groups):
            if caster is None:
                continue
            f, t = caster.faces(o, d, maxd)
            take = (f >= 0) & (t < dist)
            face[take] = fmap[f[take]]
            dist[take] = t[take]
        return face, dist

    def first_hit(self, origins, directions, max_distance=np.inf, groups=("still", "movers")) -> Hits:
        """As :meth:`RayCaster.first_hit`, the faces indexing ``mesh``: the nearest hit of ``groups``."""
        o, d = _as_rays(origins, directions)
        n = len(o)
        best = None
        for caster, fmap in (self._groups[g] for g in groups):
            if caster is None:
                continue
            h = caster.first_hit(o, d, max_distance)
            h = Hits(h.distance, np.where(h.hit, fmap[np.maximum(h.face, 0)], -1), h.part, h.material, h.normal)
            best = h if best is None else best.nearer(h)
        if best is None:
            return Hits(np.full(n, np.inf), np.full(n, -1, np.int64), np.full(n, -1), np.full(n, -1),
                        np.zeros((n, 3)))
        return best


class SceneRayCaster:
    """Ray casting over a scene: static structure (built once) plus dynamic objects (:class:`DynamicCaster`: the
    doors and the objects that move rebuilt when they move, apart from the rest).

    ``include_dynamic=False`` casts against the static structure only (what reverb probes are baked over).
    """

    def __init__(self, scene: Scene, backend: str = "embree", proxies: bool = False):
        self.scene = scene
        self.backend = backend
        self.proxies = proxies  # objects as their simple proxies (navigation), not their parts
        self.static = RayCaster(scene.static_mesh(), backend)
        self._dyn: DynamicCaster | None = None

    @property
    def dynamic(self) -> DynamicCaster:
        if self._dyn is None:
            self._dyn = DynamicCaster(self.scene, self.backend, self.proxies)
        return self._dyn.sync()

    def part_offset(self) -> int:
        """Dynamic part ids are returned shifted by this amount (the number of static parts)."""
        return len(self.scene.static_mesh().part_names)

    def part_name(self, part: int) -> str:
        off = self.part_offset()
        return self.scene.static_mesh().part_names[part] if part < off else \
            self.scene.dynamic_mesh(self.proxies).part_names[part - off]

    def first_hit(self, origins, directions, max_distance=np.inf, include_dynamic: bool = True) -> Hits:
        h = self.static.first_hit(origins, directions, max_distance)
        if not include_dynamic or not self.scene.objects:
            return h
        g = self.dynamic.first_hit(origins, directions, max_distance)
        return h.nearer(Hits(g.distance, g.face + len(self.scene.static_mesh()), g.part + self.part_offset(),
                             g.material, g.normal))

    def crossings(self, a, b, include_dynamic: bool = True, max_hits: int = 64) -> Crossings:
        """Every surface crossed by the segments a[i] -> b[i] ((n, 3) each)."""
        ray, dist, face, ci, casters = self.walk(a, b, include_dynamic, max_hits)
        if not len(ray):
            e = np.zeros(0)
            return Crossings(e.astype(np.int64), e, e.astype(np.int64), e.astype(np.int64), e.astype(bool),
                             e.astype(np.int64))
        order = np.lexsort((dist, ray))
        ray, dist, face, ci = ray[order], dist[order], face[order], ci[order]
        part = np.empty(len(ray), self.static.mesh.face_part.dtype)
        material = np.empty(len(ray), self.static.mesh.face_material.dtype)
        dynamic = np.zeros(len(ray), bool)
        glob = face.copy()  # static faces first, then the dynamic mesh's
        for k, (caster, off, dyn) in enumerate(casters):
            sel = ci == k
            if not sel.any():
                continue
            f = face[sel]
            part[sel] = caster.mesh.face_part[f] + off
            material[sel] = caster.mesh.face_material[f]
            if dyn:
                dynamic[sel] = True
                glob[sel] = f + len(self.scene.static_mesh())
        return Crossings(ray, dist, part, material, dynamic, glob)

    def walk(self, a, b, include_dynamic: bool = True, max_hits: int = 64):
        """The hits of :meth:`crossings` unsorted and unlabelled: (ray, distance, face, caster index) (k,) each, in
        the order they were found, and the casters [(RayCaster, part offset, dynamic)] the index refers to.

        Walks each segment hit by hit; the real-time occlusion path calls this per block, so a step is one Embree
        query plus a few array operations on the rays still walking (:meth:`RayCaster.faces`), not a full
        :meth:`first_hit` (an order of magnitude more overhead per step for one or two rays)."""
        a = np.atleast_2d(np.asarray(a, dtype=np.float64))
        b = np.atleast_2d(np.asarray(b, dtype=np.float64))
        seg = b - a
        length = np.linalg.norm(seg, axis=1)
        rays, dists, faces, which = [], [], [], []  # per step: the rays that hit, where, the face, the caster
        casters = [(self.static, 0, False)]
        if include_dynamic and self.scene.objects:
            casters.append((self.dynamic, self.part_offset(), True))
        start = np.flatnonzero(length > STEP_EPS)
        d0 = seg[start] / length[start, None]
        for ci, (caster, off, dyn) in enumerate(casters):
            if caster.empty or not len(start):
                continue
            active, d, travelled = start, d0, np.zeros(len(start))
            o, left = a[start], length[start]
            for _ in range(max_hits):
                face, dist = caster.faces(o + d * travelled[:, None], d, left - travelled)
                hit = face >= 0
                k = np.count_nonzero(hit)
                if k == 0:
                    break
                if k < len(hit):
                    active, d, o, left = active[hit], d[hit], o[hit], left[hit]
                    travelled, face, dist = travelled[hit], face[hit], dist[hit]
                t = travelled + dist
                rays.append(active)
                dists.append(t)
                faces.append(face)
                which.append(ci)
                travelled = t + STEP_EPS
        if not rays:
            e = np.zeros(0)
            return e.astype(np.int64), e, e.astype(np.int64), e.astype(np.int8), casters
        ci = np.repeat(np.array(which, np.int8), [len(r) for r in rays])
        return np.concatenate(rays), np.concatenate(dists), np.concatenate(faces), ci, casters

    def line_of_sight(self, a, b, include_dynamic: bool = True) -> np.ndarray:
        """(n,) bool: nothing lies between a[i] and b[i]."""
        a = np.atleast_2d(np.asarray(a, dtype=np.float64))
        b = np.atleast_2d(np.asarray(b, dtype=np.float64))
        seg = b - a
        length = np.linalg.norm(seg, axis=1)
        ok = length > STEP_EPS
        res = np.ones(len(a), dtype=bool)
        if np.any(ok):
            h = self.first_hit(a[ok], seg[ok], length[ok], include_dynamic)
            res[np.flatnonzero(ok)] = ~h.hit
        return res
