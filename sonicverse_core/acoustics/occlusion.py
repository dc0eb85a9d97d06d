"""Dynamic occlusion: per-band transmission of every surface between each source and a listener.

Embree rays through static and dynamic geometry; every part crossed (once per part) multiplies its material's
amplitude transmission per band. Rays are cast only where needed: segments whose ends moved more than a tolerance
(most-moved first, a budget per block), every segment in the block after the scene's dynamic state changes (a door),
none where no part's bounding box meets the segment, and none at all in a convex scene.
"""
from __future__ import annotations

import numpy as np

from sonicverse_core.acoustics.kernels import segment_motion
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
    """(n,) bool: does segment a->b meet any of the boxes [lo, hi] (m, 3)? (slab test)"""
    d = (b - a)[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / np.where(np.abs(d) < 1e-12, 1e-12, d)
        t0 = (lo[None] - a[:, None, :]) * inv
        t1 = (hi[None] - a[:, None, :]) * inv
    tmin = np.max(np.minimum(t0, t1), axis=2)
    tmax = np.min(np.maximum(t0, t1), axis=2)
    return np.any((tmax >= np.maximum(tmin, 0.0)) & (tmin <= 1.0), axis=1)


def _part_bounds(mesh) -> tuple[np.ndarray, np.ndarray]:
    """Bounding box (lo, hi) of every part of a SceneMesh."""
    tri = mesh.vertices[mesh.faces]
    order = np.argsort(mesh.face_part, kind="stable")
    starts = np.unique(mesh.face_part[order], return_index=True)[1]
    return np.minimum.reduceat(tri.min(1)[order], starts), np.maximum.reduceat(tri.max(1)[order], starts)


class Occlusion:
    """Occlusion state shared by a renderer's listeners; per-listener arrays live in the listener's state dict
    (``occ_target`` (n, 9), ``occ_seg`` (n, 6), ``scene_version``)."""

    def __init__(self, scene, tolerance: float, rays_per_block: int):
        from sonicverse_core.geometry.raycast import SceneRayCaster

        self.scene = scene
        self.caster = SceneRayCaster(scene)
        self.tolerance, self.budget = tolerance, rays_per_block
        self._log_trans = 0.5 * np.log(np.maximum(material_arrays()[2], 1e-12))
        self._boxes_version = None
        self.stats = {"occlusion_rays": 0, "occlusion_skipped": 0}

    def _boxes(self) -> tuple[np.ndarray, np.ndarray]:
        """Part bounding boxes of the static structure and dynamic objects, rebuilt when the scene changes."""
        if self._boxes_version != self.scene.dynamic_version:
            boxes = [_part_bounds(m) for m in (self.scene.static_mesh(), self.scene.dynamic_mesh())
                     if m is not None and len(m)]
            self._lo = np.concatenate([b[0] for b in boxes]) - 1e-3 if boxes else np.zeros((0, 3))
            self._hi = np.concatenate([b[1] for b in boxes]) + 1e-3 if boxes else np.zeros((0, 3))
            self._boxes_version = self.scene.dynamic_version
        return self._lo, self._hi

    def update(self, st: dict, pos: np.ndarray, lis: np.ndarray) -> None:
        """Recast what needs it for sources at ``pos`` (n, 3) heard at ``lis`` (3,); writes st['occ_target']."""
        n = len(pos)
        version = self.scene.dynamic_version
        if version != st["scene_version"]:
            todo = np.ones(n, bool)
            st["scene_version"] = version
        else:  # never-cast segments have NaN ends: infinitely moved, they go first
            moved = np.empty(n)
            segment_motion(pos, lis, st["occ_seg"][:n], moved)
            todo = moved > self.tolerance
            if np.count_nonzero(todo) > self.budget:
                todo = np.zeros(n, bool)
                todo[np.argpartition(-moved, self.budget)[: self.budget]] = True
        if not np.any(todo):
            return
        idx = np.flatnonzero(todo)
        a, b = pos[idx], np.broadcast_to(lis, (len(idx), 3))
        lo, hi = self._boxes()
        near = segment_meets_boxes(a, b, lo, hi) if len(lo) else np.zeros(len(idx), bool)
        cast = np.flatnonzero(near & (np.linalg.norm(b - a, axis=1) > 1e-6))
        self.stats["occlusion_rays"] += len(cast)
        self.stats["occlusion_skipped"] += len(idx) - len(cast)
        target = np.ones((len(idx), len(BANDS)))
        if len(cast):
            cr = self.caster.crossings(a[cast], b[cast])
            if len(cr.ray):
                key = cr.ray.astype(np.int64) * (int(cr.part.max()) + 1) + cr.part
                _, first = np.unique(key, return_index=True)  # a part counts once per segment
                logamp = np.zeros((len(cast), len(BANDS)))
                np.add.at(logamp, cr.ray[first], self._log_trans[cr.material[first]])
                target[cast] = np.exp(logamp)
        st["occ_target"][idx] = target
        st["occ_seg"][idx] = np.concatenate([a, b], axis=1)
