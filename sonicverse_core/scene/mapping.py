"""Semantic category -> acoustic material tables (iGibson-style, Matterport3D-style, built-in), user-overridable.

Tables from the original Sonicverse platform: iGibson static skeleton (walls and ceilings ConcreteBlockPainted,
floors WoodPanel, windows GlassThick) and its Matterport3D category table; anything unmapped is ``Uniform``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

from sonicverse_core.errors import MaterialError, SceneFileError
from sonicverse_core.scene.materials import get_material

IGIBSON = {
    "walls": "ConcreteBlockPainted", "wall": "ConcreteBlockPainted",
    "ceilings": "ConcreteBlockPainted", "ceiling": "ConcreteBlockPainted",
    "floors": "WoodPanel", "floor": "WoodPanel",
    "window": "GlassThick", "windows": "GlassThick",
}

MP3D = {
    "couch": "CurtainHeavy", "armchair": "PlywoodPanel", "ceiling": "AcousticCeilingTiles",
    "wall": "ConcreteBlockPainted", "floor": "WoodPanel", "shower floor": "PolishedConcreteOrTile",
    "shower wall": "PolishedConcreteOrTile", "blinds": "GlassThin", "kitchen shelf": "PlywoodPanel",
    "bed": "CurtainHeavy", "picture": "PlywoodPanel", "curtain": "CurtainHeavy", "sofa chair": "CurtainHeavy",
    "door": "WoodPanel", "partition": "ConcreteBlockPainted", "door frame": "PlywoodPanel", "window": "GlassThin",
    "fireplace": "BrickBare", "mirror": "GlassThin", "lighting": "GlassThin",
    # mpcat40 names that stand for the same things
    "sofa": "CurtainHeavy", "shower": "PolishedConcreteOrTile", "fireplace ": "BrickBare",
}

#: The built-in apartment: iGibson's skeleton plus the 15 sounding categories and doors.
BUILTIN = {
    **IGIBSON,
    "door": "WoodPanel", "sofa": "CurtainHeavy", "bed": "CurtainHeavy", "cushion": "CurtainHeavy",
    "picture": "PlywoodPanel", "shelf": "PlywoodPanel", "bottom_cabinet": "PlywoodPanel",
    "breakfast_table": "WoodPanel", "straight_chair": "PlywoodPanel", "stool": "PlywoodPanel",
    "standing_tv": "GlassThin", "sink": "PolishedConcreteOrTile", "toilet": "PolishedConcreteOrTile",
    "shower": "PolishedConcreteOrTile", "bathtub": "PolishedConcreteOrTile", "countertop": "Marble",
}


@dataclass(frozen=True)
class CategoryMapping:
    """Maps semantic categories (case-insensitive, '_' == ' ') to material names; unknown -> ``default``."""

    table: dict = field(default_factory=dict)
    default: str = "Uniform"
    name: str = "custom"

    def __post_init__(self):
        for mat in list(self.table.values()) + [self.default]:
            get_material(mat)  # raises MaterialError for unknown names

    @staticmethod
    def _key(category: str) -> str:
        return category.strip().lower().replace("_", " ")

    def material_for(self, category: str | None) -> str:
        if not category:
            return self.default
        norm = {self._key(k): v for k, v in self.table.items()}
        return norm.get(self._key(category), self.default)

    def updated(self, overrides: dict, name: str | None = None) -> "CategoryMapping":
        return CategoryMapping({**self.table, **overrides}, overrides.get("__default__", self.default),
                               name or self.name)


MAPPINGS = {
    "igibson": CategoryMapping(IGIBSON, name="igibson"),
    "mp3d": CategoryMapping(MP3D, name="mp3d"),
    "builtin": CategoryMapping(BUILTIN, name="builtin"),
}


def load_mapping(path: str | Path, base: str = "builtin") -> CategoryMapping:
    """A user mapping file: JSON ``{"category": "Material", ..., "__default__": "Uniform"}`` over ``base``."""
    p = Path(path)
    if not p.is_file():
        raise SceneFileError(f"material mapping file not found: {p}")
    try:
        data = json.loads(p.read_text())
    except (OSError, ValueError) as exc:
        raise SceneFileError(f"material mapping file {p} is not valid JSON: {exc}") from None
    if not isinstance(data, dict) or not all(isinstance(v, str) for v in data.values()):
        raise MaterialError(f"material mapping file {p} must map category names to material names")
    return MAPPINGS[base].updated({k: v for k, v in data.items()}, name=f"{base}+{p.name}")
