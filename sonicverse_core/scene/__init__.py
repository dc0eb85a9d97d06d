"""Scenes: static structure, dynamic objects, rooms, semantics, acoustic materials; loaders and generators."""
from sonicverse_core.scene.materials import BANDS, MATERIAL_NAMES, MATERIALS, Material, get_material  # noqa: F401
from sonicverse_core.scene.model import Door, Room, Scene, SceneObject, StaticPart, StructureKind  # noqa: F401
from sonicverse_core.scene.spec import load_scene  # noqa: F401
