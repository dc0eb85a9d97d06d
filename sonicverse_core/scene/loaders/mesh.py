"""GLB/glTF, OBJ and PLY scenes through trimesh.

Each geometry (node; in OBJ files each object and group) becomes a part. Its category is the node or geometry name without numeric suffixes ('wall.001'
-> 'wall'). Structure categories (walls, floors, ceilings, windows, columns...) form the static structure; everything
else is a dynamic object. A geometry whose visual material is named after an acoustic material gets that material,
else its category's material through the mapping, else ``Uniform``. Rooms are segmented from the free floor
(regions joined by narrow openings, :mod:`sonicverse_core.geometry.rooms`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from sonicverse_core.errors import MeshError, SceneFileError
from sonicverse_core.scene.loaders.common import STRUCTURE, category_of_name, material_for
from sonicverse_core.scene.mapping import CategoryMapping
from sonicverse_core.scene.model import Room, Scene, SceneObject, StaticPart, StructureKind, check_mesh

MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply")


def load_mesh_scene(path: str | Path, mapping: CategoryMapping, spec: str | None = None) -> Scene:
    p = Path(path)
    if not p.exists():
        raise SceneFileError(f"scene file not found: {p}")
    if p.suffix.lower() not in MESH_SUFFIXES:
        raise SceneFileError(f"unsupported scene file type '{p.suffix}'; use one of {', '.join(MESH_SUFFIXES)}")
    try:
        # OBJ: every `o` object and `g` group is a part of its own (trimesh merges them by material otherwise)
        extra = {"group_material": False, "split_objects": True, "split_groups": True} \
            if p.suffix.lower() == ".obj" else {}
        loaded = trimesh.load(str(p), force="scene", process=False, **extra)
    except Exception as exc:  # trimesh raises many types for broken files
        raise SceneFileError(f"cannot read {p}: {exc}") from None
    static, objects = [], []
    names: set[str] = set()
    for node in loaded.graph.nodes_geometry:
        transform, geom_name = loaded.graph[node]
        geom = loaded.geometry[geom_name]
        if not isinstance(geom, trimesh.Trimesh):
            continue
        mesh = geom.copy()
        mesh.apply_transform(transform)
        name = str(node)
        check_mesh(mesh, f"{p.name}:{name}")
        category = category_of_name(name, mapping)
        vis_mat = getattr(getattr(mesh.visual, "material", None), "name", None)
        material = material_for(vis_mat, category, mapping)
        unique = name
        i = 1
        while unique in names:
            unique = f"{name}#{i}"
            i += 1
        names.add(unique)
        kind = STRUCTURE.get(category)
        if kind is not None:
            static.append(StaticPart(unique, kind, category, material, mesh))
        else:
            objects.append(SceneObject(unique, category, material, mesh, np.eye(4)))
    if not static and not objects:
        raise MeshError(f"{p}: no triangle meshes found")
    if not static:  # a plain mesh with no structure names: all of it is static structure
        static = [StaticPart(o.name, StructureKind.OTHER, o.category, o.material, o.mesh) for o in objects]
        objects = []
    scene = Scene(p.stem, static, objects, [], spec=spec or str(p), mapping_name=mapping.name,
                  metadata={"source": str(p)})
    b = scene.bounds
    if np.any(b[1] - b[0] <= 1e-6):
        raise MeshError(f"{p}: the geometry is flat or empty (bounds {b.tolist()}); a room needs volume")
    from sonicverse_core.geometry.navgrid import NavGrid
    from sonicverse_core.geometry.rooms import segment_rooms

    # a mesh names no rooms: regions of free floor joined by narrow openings (sonicverse_core/geometry/rooms.py)
    scene.rooms = segment_rooms(NavGrid(scene))
    if not scene.rooms:  # no free floor at all: the bounding box stands for the one room
        lo, hi = b
        scene.rooms = [Room("scene", "unknown", np.array([(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]),
                                                          (lo[0], hi[1])]), float(lo[2]), float(hi[2]))]
    return scene
