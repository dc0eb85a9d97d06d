"""Matterport3D house folders: ``<id>.house`` + ``<id>.ply`` (faces carry face_material, face_segment,
face_category), loaded as ``mp3d:DIR``.

As in the original platform the whole mesh is static (it is one scan) and is used for baking; face categories
(C lines: raw category name and mpcat40 name) map to materials through the Matterport3D table, the raw name first.
Regions (R lines) become rooms from their bounding boxes.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from sonicverse_core.errors import SceneFileError
from sonicverse_core.scene.loaders.common import STRUCTURE
from sonicverse_core.scene.mapping import CategoryMapping
from sonicverse_core.scene.model import Room, Scene, StaticPart, StructureKind, check_mesh

REGION_LABELS = {
    "a": "bathroom", "b": "bedroom", "c": "closet", "d": "dining room", "e": "entryway", "f": "familyroom",
    "g": "garage", "h": "hallway", "i": "library", "j": "laundryroom", "k": "kitchen", "l": "living room",
    "m": "meetingroom", "n": "lounge", "o": "office", "p": "porch", "r": "rec room", "s": "stairs", "t": "toilet",
    "u": "utility room", "v": "tv", "w": "gym", "x": "outdoor", "y": "balcony", "z": "other room", "B": "bar",
    "C": "classroom", "D": "dining booth", "S": "spa", "Z": "junk", "-": "no label",
}


def parse_house(path: Path) -> tuple[dict[int, tuple[str, str]], list[Room]]:
    """Category index -> (raw name, mpcat40 name), and rooms from the R lines."""
    cats, rooms = {}, []
    for ln, line in enumerate(path.read_text().splitlines(), 1):
        f = line.split()
        if not f:
            continue
        try:
            if f[0] == "C":
                # C category_index category_mapping_index category_mapping_name mpcat40_index mpcat40_name ...
                cats[int(f[1])] = (f[3].replace("#", " "), f[5].replace("#", " "))
            elif f[0] == "R":
                # R region_index level_index 0 0 label px py pz xlo ylo zlo xhi yhi zhi height ...
                idx, label = int(f[1]), f[5]
                xlo, ylo, zlo, xhi, yhi, zhi = map(float, f[9:15])
                rtype = REGION_LABELS.get(label, "other room")
                rooms.append(Room(f"{rtype} {idx}", rtype, np.array([(xlo, ylo), (xhi, ylo), (xhi, yhi), (xlo, yhi)]),
                                  zlo, zhi))
        except (IndexError, ValueError):
            raise SceneFileError(f"{path}:{ln}: malformed {f[0]} line") from None
    return cats, rooms


def load_mp3d(folder: str | Path, mapping: CategoryMapping, spec: str | None = None) -> Scene:
    d = Path(folder)
    if not d.is_dir():
        raise SceneFileError(f"Matterport3D folder not found: {d}")
    houses = sorted(d.glob("*.house"))
    if not houses:
        raise SceneFileError(f"{d}: no .house file (a Matterport3D house folder has <id>.house and <id>.ply)")
    house = houses[0]
    ply = house.with_suffix(".ply")
    if not ply.is_file():
        plys = sorted(d.glob("*.ply"))
        if not plys:
            raise SceneFileError(f"{d}: no .ply mesh next to {house.name}")
        ply = plys[0]
    cats, rooms = parse_house(house)
    try:
        mesh = trimesh.load(str(ply), process=False)
    except Exception as exc:
        raise SceneFileError(f"cannot read {ply}: {exc}") from None
    check_mesh(mesh, ply.name)
    raw = mesh.metadata.get("_ply_raw", {}).get("face", {}).get("data", {})
    if "face_category" not in raw:
        raise SceneFileError(f"{ply}: faces carry no face_category property (not a Matterport3D house mesh)")
    face_cat = np.asarray(raw["face_category"]).reshape(-1).astype(np.int64)
    static = []
    for c in np.unique(face_cat):
        raw_name, mpcat = cats.get(int(c), ("unlabeled", "unlabeled"))
        category = raw_name if mapping.material_for(raw_name) != mapping.default else mpcat
        sub = mesh.submesh([np.flatnonzero(face_cat == c)], append=True)
        kind = STRUCTURE.get(mpcat, STRUCTURE.get(raw_name, StructureKind.OTHER))
        static.append(StaticPart(f"{category} ({int(c)})", kind, category, mapping.material_for(category), sub))
    return Scene(house.stem, static, [], rooms, spec=spec or f"mp3d:{d}", mapping_name=mapping.name,
                 metadata={"source": str(d), "format": "mp3d"})
