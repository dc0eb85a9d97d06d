"""What the loaders share: structure categories and the material rule for named geometry."""
from __future__ import annotations

import re

from sonicverse_core.scene.mapping import CategoryMapping
from sonicverse_core.scene.materials import MATERIALS
from sonicverse_core.scene.model import StructureKind

STRUCTURE = {
    "wall": StructureKind.WALL, "walls": StructureKind.WALL, "partition": StructureKind.WALL,
    "floor": StructureKind.FLOOR, "floors": StructureKind.FLOOR, "shower floor": StructureKind.FLOOR,
    "ceiling": StructureKind.CEILING, "ceilings": StructureKind.CEILING,
    "window": StructureKind.WINDOW, "windows": StructureKind.WINDOW,
    "shower wall": StructureKind.WALL, "column": StructureKind.OTHER, "beam": StructureKind.OTHER,
    "stairs": StructureKind.OTHER, "railing": StructureKind.OTHER,
}


def category_of_name(name: str, mapping: CategoryMapping | None = None) -> str:
    """'Chair.001', 'chair_3', 'wall-2' -> 'chair', 'wall'; 'wall_north' -> 'wall' when 'wall_north' is not
    itself a known category but its first word is."""
    base = re.split(r"[.\-#]", name.strip())[0]
    base = re.sub(r"[_ ]?\d+$", "", base).strip().lower().replace("-", " ")
    known = (lambda c: c in STRUCTURE or (mapping is not None and mapping.material_for(c) != mapping.default))
    if not known(base):
        first = re.split(r"[_ .\-#\d]", base)[0]
        if first and known(first):
            return first
    return base


def material_for(material_name: str | None, category: str, mapping: CategoryMapping) -> str:
    """The acoustic material name given a visual material name (wins if it names an acoustic material),
    else the category through the mapping (else the mapping's default)."""
    if material_name:
        for m in MATERIALS:
            if m.lower() == material_name.strip().lower():
                return m
    return mapping.material_for(category)
