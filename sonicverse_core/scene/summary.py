"""Scene summaries for `sonicverse scene info`."""
from __future__ import annotations

from collections import Counter

import numpy as np

from sonicverse_core.scene.model import Door, Scene


VERTEX_BYTES = 4 * (3 + 3 + 4)  # pyrender's flat-shaded vertex: position, normal, colour (float32)


def _look_info(scene: Scene) -> dict:
    """The home's look (baked or from the cache): triangles after cutting at the texture grid, the vertex buffers
    (position, normal, uv, colour: 48 bytes a vertex), the texture atlas with its mipmaps, the bake's seconds."""
    from sonicverse_core.scene.look import atlas, home_look

    lk = home_look(scene)
    img, _ = atlas()
    return {"triangles": lk.triangles, "vertex_bytes": lk.vertex_bytes, "vertex_mib": round(lk.vertex_bytes / 2**20, 3),
            "texture": f"{img.shape[1]}x{img.shape[0]} RGBA8 + mipmaps", "texture_bytes": lk.texture_bytes,
            "texture_mib": round(lk.texture_bytes / 2**20, 3),
            "total_mib": round((lk.vertex_bytes + lk.texture_bytes) / 2**20, 3),
            "bake_s": round(lk.bake_s, 3), "from_cache": lk.cached}


def scene_info(scene: Scene, nav_area: float | None = None, look: bool = True) -> dict:
    """Rooms, objects per category, materials with their surface areas (m^2: the structure's and every object
    part's), floor area, bounds, triangles, and the look's size in the renderer (``visual``: the flat look;
    ``look``: the home's textured look with baked light, what the cameras and the VR views draw)."""
    areas: Counter = Counter()
    for p in scene.static:
        areas[p.material] += float(p.mesh.area)
    parts = 0
    for o in scene.objects:  # what the ear hears: each part's surface in its own material
        for _, mat, m, _ in o.looks():
            areas[mat] += float(m.area)
            parts += 1
    tris = scene.triangle_count
    floor = sum(r.area for r in scene.rooms) if scene.rooms else 0.0
    info = {
        "name": scene.name,
        "spec": scene.spec,
        "mapping": scene.mapping_name,
        "bounds": np.round(scene.bounds, 3).tolist(),
        "floor_area_m2": round(floor, 2),
        "triangles": scene.triangle_count,
        "static_triangles": len(scene.static_mesh()),
        "rooms": [{"name": r.name, "type": r.type, "area_m2": round(r.area, 2),
                   "height_m": round(r.z_ceiling - r.z_floor, 3)} for r in scene.rooms],
        "objects_per_category": dict(sorted(Counter(o.category for o in scene.objects).items())),
        "doors": [{"name": d.name, "rooms": list(d.rooms), "open_fraction": d.open_fraction}
                  for d in scene.objects if isinstance(d, Door)],
        "materials_m2": {k: round(v, 2) for k, v in sorted(areas.items())},
        # what the eye's renderer uploads: flat-shaded triangles, 3 vertices each of position, normal and RGBA
        # colour, all float32 (pyrender) = 120 bytes a triangle (the robot's camera keeps one copy, the VR views
        # another)
        "visual": {"triangles": tris, "object_parts": parts, "buffer_bytes": VERTEX_BYTES * 3 * tris,
                   "buffer_mib": round(VERTEX_BYTES * 3 * tris / 2**20, 3)},
        "look": _look_info(scene) if look else None,
        "metadata": {k: v for k, v in scene.metadata.items() if isinstance(v, (int, float, str, list))},
    }
    if nav_area is not None:
        info["navigable_area_m2"] = round(nav_area, 2)
    return info
