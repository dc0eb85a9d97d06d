"""Geometry: Embree ray casting, navigability grids, geodesic distances."""
from sonicverse_core.geometry.navgrid import NavConfig, NavGrid  # noqa: F401
from sonicverse_core.geometry.raycast import Crossings, Hits, RayCaster, SceneRayCaster  # noqa: F401
