"""iGibson scene folders, loaded as ``igibson:DIR``: ``urdf/<scene>_best.urdf`` whose links carry a ``category``
and OBJ visual meshes (with joint origins), and ``layout/floor_trav_0.png`` (traversability at 1 cm per pixel,
centred on the origin, as iGibson writes it).

Only the static skeleton (walls, floors, ceilings, windows) is static structure, since everything else can move;
the other links become dynamic objects (doors among them).
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import trimesh

from sonicverse_core.errors import SceneFileError
from sonicverse_core.scene.loaders.common import STRUCTURE
from sonicverse_core.scene.mapping import CategoryMapping
from sonicverse_core.scene.model import Room, Scene, SceneObject, StaticPart, check_mesh

TRAV_RESOLUTION = 0.01


def _origin(el) -> np.ndarray:
    m = np.eye(4)
    if el is None:
        return m
    xyz = [float(v) for v in el.get("xyz", "0 0 0").split()]
    r, p, y = [float(v) for v in el.get("rpy", "0 0 0").split()]
    m[:3, :3] = trimesh.transformations.euler_matrix(r, p, y, "sxyz")[:3, :3]
    m[:3, 3] = xyz
    return m


def load_igibson(folder: str | Path, mapping: CategoryMapping, spec: str | None = None) -> Scene:
    d = Path(folder)
    if not d.is_dir():
        raise SceneFileError(f"iGibson scene folder not found: {d}")
    urdfs = sorted((d / "urdf").glob("*_best.urdf")) or sorted((d / "urdf").glob("*.urdf"))
    if not urdfs:
        raise SceneFileError(f"{d}: no urdf/<scene>_best.urdf")
    urdf = urdfs[0]
    try:
        root = ET.parse(urdf).getroot()
    except ET.ParseError as exc:
        raise SceneFileError(f"{urdf}: not valid XML ({exc})") from None
    # world pose of each link from the joint tree
    parent_of = {}
    for j in root.findall("joint"):
        parent_of[j.find("child").get("link")] = (j.find("parent").get("link"), _origin(j.find("origin")))

    def world(link: str, depth=0) -> np.ndarray:
        if link not in parent_of or depth > 64:
            return np.eye(4)
        parent, t = parent_of[link]
        return world(parent, depth + 1) @ t

    static, objects = [], []
    for link in root.findall("link"):
        name = link.get("name")
        category = (link.get("category") or name).lower()
        meshes = []
        for vis in link.findall("visual"):
            g = vis.find("geometry/mesh")
            if g is None:
                continue
            f = (urdf.parent / g.get("filename")).resolve()
            if not f.is_file():
                raise SceneFileError(f"{urdf.name}: link '{name}' mesh not found: {f}")
            try:
                m = trimesh.load(str(f), force="mesh", process=False)
            except Exception as exc:
                raise SceneFileError(f"cannot read {f}: {exc}") from None
            scale = [float(v) for v in g.get("scale", "1 1 1").split()]
            m.apply_scale(scale)
            m.apply_transform(_origin(vis.find("origin")))
            meshes.append(m)
        if not meshes:
            continue
        mesh = trimesh.util.concatenate(meshes)
        check_mesh(mesh, f"{urdf.name}:{name}")
        pose = world(name)
        material = mapping.material_for(category)
        kind = STRUCTURE.get(category)
        if kind is not None:
            mesh.apply_transform(pose)
            static.append(StaticPart(name, kind, category, material, mesh))
        else:
            objects.append(SceneObject(name, category, material, mesh, pose, movable=category != "door"))
    meta = {"source": str(d), "format": "igibson"}
    trav = d / "layout" / "floor_trav_0.png"
    if trav.is_file():
        from PIL import Image

        img = np.asarray(Image.open(trav).convert("L")) > 0
        meta["traversable"] = img
        meta["traversable_resolution"] = TRAV_RESOLUTION
    scene = Scene(urdf.stem.replace("_best", ""), static, objects, [], spec=spec or f"igibson:{d}",
                  mapping_name=mapping.name, metadata=meta)
    lo, hi = scene.bounds
    scene.rooms = [Room("scene", "unknown", np.array([(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])]),
                        float(lo[2]), float(hi[2]))]
    return scene


def traversable_at(scene: Scene, xy: np.ndarray) -> np.ndarray:
    """iGibson's traversability map at points (n, 2): row = y/res + size/2, col = x/res + size/2."""
    img = scene.metadata["traversable"]
    res = scene.metadata["traversable_resolution"]
    rc = np.floor(xy[:, ::-1] / res + np.array(img.shape) / 2).astype(np.int64)
    ok = (rc[:, 0] >= 0) & (rc[:, 0] < img.shape[0]) & (rc[:, 1] >= 0) & (rc[:, 1] < img.shape[1])
    out = np.zeros(len(xy), dtype=bool)
    out[ok] = img[rc[ok, 0], rc[ok, 1]]
    return out

