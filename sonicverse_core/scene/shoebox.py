"""Shoebox rooms for analytic checks: ``shoebox:LxWxH?material=NAME`` spans (0, 0, 0) to (L, W, H), z up.

Per-surface materials: ``floor=``, ``ceiling=``, ``walls=`` (all four), or ``x0=``, ``x1=``, ``y0=``, ``y1=``
for the walls at x=0, x=L, y=0, y=W.
"""
from __future__ import annotations

import numpy as np
import trimesh

from sonicverse_core.errors import MeshError
from sonicverse_core.scene.materials import get_material
from sonicverse_core.scene.model import Room, Scene, StaticPart, StructureKind

SURFACES = ("floor", "ceiling", "x0", "x1", "y0", "y1")


def quad(corners: np.ndarray) -> trimesh.Trimesh:
    """Two triangles over 4 corners given counter-clockwise as seen from the side the normal points to."""
    return trimesh.Trimesh(vertices=np.asarray(corners, float), faces=[[0, 1, 2], [0, 2, 3]], process=False)


def shoebox_surfaces(L: float, W: float, H: float) -> dict[str, np.ndarray]:
    """The six inner surfaces' corners, normals pointing into the room."""
    return {
        "floor": [(0, 0, 0), (L, 0, 0), (L, W, 0), (0, W, 0)],
        "ceiling": [(0, 0, H), (0, W, H), (L, W, H), (L, 0, H)],
        "x0": [(0, 0, 0), (0, W, 0), (0, W, H), (0, 0, H)],
        "x1": [(L, 0, 0), (L, 0, H), (L, W, H), (L, W, 0)],
        "y0": [(0, 0, 0), (0, 0, H), (L, 0, H), (L, 0, 0)],
        "y1": [(0, W, 0), (L, W, 0), (L, W, H), (0, W, H)],
    }


def make_shoebox(L: float, W: float, H: float, materials: dict[str, str] | None = None,
                 spec: str | None = None) -> Scene:
    """A closed rectangular room. ``materials`` maps surface names (see :data:`SURFACES`) to material names."""
    dims = np.array([L, W, H], dtype=float)
    if not np.all(np.isfinite(dims)) or np.any(dims <= 0):
        raise MeshError(f"shoebox dimensions must be positive and finite, got {L}x{W}x{H} (zero volume)")
    mats = {s: "Uniform" for s in SURFACES}
    for k, v in (materials or {}).items():
        if k not in SURFACES:
            raise MeshError(f"unknown shoebox surface '{k}'; use one of {', '.join(SURFACES)}")
        get_material(v)
        mats[k] = v
    kinds = {"floor": StructureKind.FLOOR, "ceiling": StructureKind.CEILING}
    parts = []
    for name, corners in shoebox_surfaces(L, W, H).items():
        kind = kinds.get(name, StructureKind.WALL)
        parts.append(StaticPart(name, kind, kind.value, mats[name], quad(np.array(corners, float)), room="room"))
    room = Room("room", "shoebox", np.array([(0, 0), (L, 0), (L, W), (0, W)], float), 0.0, H)
    return Scene(f"shoebox {L:g}x{W:g}x{H:g}", parts, [], [room], spec=spec, mapping_name="explicit",
                 metadata={"dimensions": [L, W, H], "surface_materials": mats})
