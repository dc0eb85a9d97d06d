"""Dynamic occlusion: per-band transmission of every surface between each source and a listener.

Embree rays through static and dynamic geometry; every part crossed (once per part) multiplies its material's
amplitude transmission per band. Rays are cast only where needed: segments whose ends moved more than a tolerance
(most-moved first, a budget per block), in the block after the scene's dynamic state changes (a door) every segment
that meets the box of an object that moved (before or after its move), none where no part's bounding box meets
the segment, and none at all in a convex scene.
"""
from __future__ import annotations

import numpy as np

from sonicverse_core.acoustics.kernels import count_over, occlusion_logs, segment_motion, segments_meet_boxes
from sonicverse_core.acoustics.state import PerSource
from sonicverse_core.scene.materials import BANDS, material_arrays


def may_occlude(scene) -> bool:
    """False when no geometry can lie between two points inside the scene: no static mesh, or a convex static
    structure (every vertex on the inner side of every face plane) and no dynamic objects."""
    mesh = scene.static_mesh()
    if scene.objects or len(mesh) > 2000:
        return True
    if len(mesh) == 0:
        return False
    v, f = mesh.vertices, mesh.faces
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    # orient normals inward (towards the centroid) and check that no vertex lies outside any face plane
    side = np.einsum("ij,ij->i", v.mean(0) - tri[:, 0], n)
    n = np.where(side[:, None] < 0, -n, n)
    dist = np.einsum("fvk,fk->fv", v[None, :, :] - tri[:, None, 0, :], n)
    return bool(np.any(dist < -1e-6))


def segment_meets_boxes(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(n,) bool: does segment a->b meet any of the boxes [lo, hi] (m, 3)? (slab test; the twin of the compiled
    ``kernels.segments_meet_boxes``, which the recast uses)"""
    d = (b - a)[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(np.abs(d) < 1e-12, 1e-12, d)
        t0 = (lo[None] - a[:, None, :]) * inv
        t1 = (hi[None] - a[:, None, :]) * inv
    tmin = np.max(np.minimum(t0, t1), axis=2)
    tmax = np.min(np.maximum(t0, t1), axis=2)
    return np.any((tmax >= np.maximum(tmin, 0.0)) & (tmin <= 1.0), axis=1)


def sounding_bounds(scene, kept: dict | None = None) -> np.ndarray:
    """(m, 2, 3): each object's world bounds, 1 cm wider, in the scene's order (its part in the dynamic mesh);
    a door's is empty (a door is not where a sound comes from). ``kept``: object name -> (its pose's bytes, its
    bounds), filled and read here, so that only the objects that moved since are made again."""
    from sonicverse_core.scene.model import Door

    b = np.empty((len(scene.objects), 2, 3))
    for i, o in enumerate(scene.objects):
        if isinstance(o, Door):
            b[i] = ((np.inf,) * 3, (-np.inf,) * 3)
            continue
        key = o.pose.tobytes() if kept is not None else None
        hit = kept.get(o.name) if kept is not None else None
        if hit is None or hit[0] != key:
            hit = (key, o.world_bounds() + [[-0.01], [0.01]])
            if kept is not None:
                kept[o.name] = hit
        b[i] = hit[1]
    return b


def own_object_crossings(bounds: np.ndarray, offset: int, cr, starts: np.ndarray) -> np.ndarray:
    """(k,) bool: which of the crossings ``cr`` (of segments starting at ``starts`` (n, 3), a source's end) cross an
    object whose ``bounds`` (:func:`sounding_bounds`; its part is ``offset`` + its index) hold the segment's start:
    the object the sound comes from (a TV, a toilet, a cushion: :meth:`~sonicverse_core.scene.model.SceneObject.
    sound_position` is the centre of its bounds). A sounding object radiates from its own surface, so its own parts
    do not occlude it. Before session 22 they did: in 7 of 12 AudioGoal episodes the goal's direct sound passed
    through its own object's material (a toilet's, a shower's, a picture's)."""
    out = np.zeros(len(cr.ray), bool)
    if len(cr.ray) == 0 or not np.any(cr.dynamic):
        return out
    k = cr.part - offset  # dynamic parts: one per object, in the scene's order
    j = np.flatnonzero(cr.dynamic & (k >= 0) & (k < len(bounds)))
    p = starts[cr.ray[j]]
    out[j] = np.all((p >= bounds[k[j], 0]) & (p <= bounds[k[j], 1]), axis=1)
    return out


def _part_bounds(mesh) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box (lo, hi) of every part of a SceneMesh."""
    tri = mesh.vertices[mesh.faces]
    order = np.argsort(mesh.face_part, kind="stable")
    starts = np.unique(mesh.face_part[order], return_index=True)[1]
    return np.minimum.reduceat(tri.min(1)[order], starts), np.maximum.reduceat(tri.max(1)[order], starts)


class OcclusionState(PerSource):
    """A listener's occlusion: per source the segment its rays were last cast along (``seg`` (6,), NaN: never) and
    how far it has moved since (``moved``); the scene version they were cast in."""

    __slots__ = ("seg", "moved", "scene_version")
    ROWS = (("seg", (6,), np.float64, np.nan), ("moved", (), np.float64, 0.0))

    def __init__(self, cap: int):
        super().__init__(cap)
        self.scene_version = None


class Occlusion:
    """The occlusion subsystem (:class:`~sonicverse_core.acoustics.state.Subsystem`): the ray caster and part boxes
    shared by a renderer's listeners; each listener's :class:`OcclusionState`. It writes the listener's
    ``occ_target`` (per source and band, the amplitude through the parts crossed)."""

    name = "occlusion"

    def __init__(self, scene, tolerance: float, rays_per_block: int):
        from sonicverse_core.geometry.raycast import SceneRayCaster

        self.scene = scene
        self.caster = SceneRayCaster(scene)
        self.tolerance, self.budget = tolerance, rays_per_block
        self._log_trans = 0.5 * np.log(np.maximum(material_arrays()[2], 1e-12))
        self._boxes_version = None
        self._bounds = (None, None)  # (scene version, sounding_bounds)
        self._sb: dict = {}  # sounding_bounds' kept: object name -> (its pose's bytes, its sounding bounds)
        self._poses = {o.name: o.pose.copy() for o in scene.objects}
        self._dirty_version, self._dirty = scene.dynamic_version, None
        self.stats = {"occlusion_rays": 0, "occlusion_skipped": 0}

    def _changed_boxes(self):
        """(lo, hi) boxes (before and after) of the objects that moved since the previous scene version, or None
        when the set of objects changed (everything is recast then)."""
        if self._dirty_version != self.scene.dynamic_version:
            objs = self.scene.objects
            if set(self._poses) != {o.name for o in objs}:
                self._dirty = None
            else:
                lo, hi = [], []
                for o in objs:
                    old = self._poses[o.name]
                    if not np.array_equal(old, o.pose):
                        for pose in (old, o.pose):
                            b = o.world_bounds(pose)
                            lo.append(b[0] - 0.01)
                            hi.append(b[1] + 0.01)
                self._dirty = (np.array(lo).reshape(-1, 3), np.array(hi).reshape(-1, 3))
            self._poses = {o.name: o.pose.copy() for o in objs}
            self._dirty_version = self.scene.dynamic_version
        return self._dirty

    def _boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """Part bounding boxes of the static structure (once) and dynamic objects (when the scene changes)."""
        if self._boxes_version != self.scene.dynamic_version:
            if not hasattr(self, "_static_boxes"):
                m = self.scene.static_mesh()
                self._static_boxes = _part_bounds(m) if len(m) else (np.zeros((0, 3)), np.zeros((0, 3)))
            d = self._object_bounds()
            self._lo = np.concatenate([self._static_boxes[0], d[0]]) - 1e-3
            self._hi = np.concatenate([self._static_boxes[1], d[1]]) + 1e-3
            self._boxes_version = self.scene.dynamic_version
        return self._lo, self._hi

    def _object_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) of every dynamic part (one per object, :func:`_part_bounds` of the dynamic mesh), each object's
        kept while its pose is: a door that moves costs its own box, not every object's."""
        dyn = self.scene.dynamic_mesh()
        if dyn is None or not len(dyn):
            return np.zeros((0, 3)), np.zeros((0, 3))
        objs = self.scene.objects
        names = tuple(o.name for o in objs)
        if getattr(self, "_ob_names", None) != names or len(dyn.part_names) != len(objs):
            self._ob_names, self._ob = names, {}
        P = len(dyn.part_names)
        ends = np.searchsorted(dyn.face_part, np.arange(P + 1))  # the dynamic mesh's faces run object by object
        lo, hi = np.full((P, 3), np.inf), np.full((P, 3), -np.inf)
        for k, o in enumerate(objs):
            key = o.pose.tobytes()
            hit = self._ob.get(k)
            if hit is None or hit[0] != key:
                f = dyn.faces[ends[k]:ends[k + 1]]
                v = dyn.vertices[f.reshape(-1)] if len(f) else np.zeros((0, 3))
                hit = self._ob[k] = (key, v.min(0) if len(v) else lo[k], v.max(0) if len(v) else hi[k])
            lo[k], hi[k] = hit[1], hit[2]
        keep = np.isfinite(lo[:, 0])  # as _part_bounds: parts without faces have no box
        return lo[keep], hi[keep]

    def prepare(self) -> None:
        """Build what the next update needs after a scene change (dynamic mesh, its ray caster, part boxes, the
        moved objects' boxes), so that a real-time caller can spread a door's cost over the blocks
        (``AcousticRenderer.set_doors``)."""
        self.caster.dynamic
        self._boxes()
        self._changed_boxes()

    # --- the subsystem protocol ----------------------------------------------------------------------------------
    def state(self, cap: int) -> OcclusionState:
        return OcclusionState(cap)

    def grow(self, state: OcclusionState | None, cap: int) -> None:
        if state is not None:
            state.grow(cap)

    def max_delay(self) -> float:
        return 0.0

    def render(self, state: OcclusionState, ls, lis, out) -> None:
        self.update(state, ls.pos, lis.position, ls.occ_target)

    def reset(self, state: OcclusionState) -> None:
        pass

    def update(self, st: OcclusionState, pos: np.ndarray, lis: np.ndarray, occ_target: np.ndarray) -> None:
        """Recast what needs it for sources at ``pos`` (n, 3) heard at ``lis`` (3,); writes their rows of
        ``occ_target`` (cap, 9)."""
        n = len(pos)
        lis = np.asarray(lis, np.float64)
        version = self.scene.dynamic_version
        # never-cast segments have NaN ends: infinitely moved, they go first
        moved = st.moved[:n]
        segment_motion(pos, lis, st.seg[:n], moved)
        if version == st.scene_version and not count_over(moved, self.tolerance):
            return  # the steady state: nothing moved, nothing cast, nothing allocated
        todo = moved > self.tolerance
        if np.count_nonzero(todo) > self.budget:
            todo = np.zeros(n, bool)
            todo[np.argpartition(-moved, self.budget)[: self.budget]] = True
        if version != st.scene_version:  # a door or an object moved: recast, now, every segment it may affect
            dirty = self._changed_boxes() if st.scene_version is not None else None
            if dirty is None:
                todo[:] = True
            elif len(dirty[0]):
                met = np.empty(n, bool)
                segments_meet_boxes(pos, lis, *dirty, met)
                todo |= met
            st.scene_version = version
        if not np.any(todo):
            return
        idx = np.flatnonzero(todo)
        a = pos[idx]
        lo, hi = self._boxes()
        near = np.zeros(len(idx), bool)
        if len(lo):
            segments_meet_boxes(a, lis, lo, hi, near)
        cast = np.flatnonzero(near & (np.linalg.norm(lis - a, axis=1) > 1e-6))
        self.stats["occlusion_rays"] += len(cast)
        self.stats["occlusion_skipped"] += len(idx) - len(cast)
        occ_target[idx] = 1.0
        if len(cast):
            ac = a[cast]
            ray, dist, face, ci, casters = self.caster.walk(ac, np.broadcast_to(lis, (len(cast), 3)))
            if self._bounds[0] != version:
                self._bounds = (version, sounding_bounds(self.scene, self._sb))
            sm = casters[0][0].mesh
            dm = casters[1][0].mesh if len(casters) > 1 else sm
            logamp = np.empty((len(cast), len(BANDS)))
            occlusion_logs(ray, dist, face, ci, sm.face_part, sm.face_material, dm.face_part, dm.face_material,
                           self.caster.part_offset(), self._bounds[1], ac, self._log_trans, logamp)
            occ_target[idx[cast]] = np.exp(logamp)  # a part counts once per segment; not its own object's
        st.seg[idx, :3] = a
        st.seg[idx, 3:] = lis
