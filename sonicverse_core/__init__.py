"""Sonicverse core: headless scenes, geometry, acoustics, world, sensors and tasks.

Importing this package loads numpy only; subsystems are imported from their own modules
(``sonicverse_core.scene``, ``sonicverse_core.geometry``, ``sonicverse_core.acoustics``...). It never imports torch,
pyrender, PyQt6, openvr or sounddevice at module level.
"""
__version__ = "0.1.0"

from sonicverse_core.errors import SonicverseError  # noqa: F401
