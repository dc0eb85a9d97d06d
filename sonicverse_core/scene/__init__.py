"""Scenes: static structure, dynamic objects, rooms, semantics, acoustic materials; loaders and generators.

The scene model and the loaders (which import trimesh, about 0.5 s) load on first use, so that reading the
material tables (``sonicverse_core.scene.materials``) stays cheap: the CLI builds its parser from them."""
from sonicverse_core.scene.materials import BANDS, MATERIAL_NAMES, MATERIALS, Material, get_material  # noqa: F401

_LAZY = {"Door": "model", "Room": "model", "Scene": "model", "SceneObject": "model", "StaticPart": "model",
         "StructureKind": "model", "load_scene": "spec"}

__all__ = ["BANDS", "MATERIAL_NAMES", "MATERIALS", "Material", "get_material", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        value = getattr(importlib.import_module(f"sonicverse_core.scene.{_LAZY[name]}"), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'sonicverse_core.scene' has no attribute {name!r}")
