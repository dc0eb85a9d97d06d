"""The visual scene built from the core scene: one pyrender scene, dynamic objects (doors, carried things) as nodes
whose poses follow the core scene, and a stereo camera rig. pyrender is imported here only (lazily by callers).

Offscreen rendering goes through EGL (PYOPENGL_PLATFORM=egl, set before the first OpenGL import): Mesa's llvmpipe
on a CPU, the GPU's driver where there is one. Create it inside the process (or worker) that renders.
"""
from __future__ import annotations

import numpy as np

from sonicverse_core.sensors.camera import RenderScene, camera_matrix as head_matrix  # sets PYOPENGL_PLATFORM=egl

IPD = 0.064  # m between the eyes (adult average)


class VisualScene:
    """pyrender scene of a core scene; ``sync()`` copies dynamic poses, ``render_stereo(head)`` draws both eyes."""

    def __init__(self, scene, width: int = 512, height: int = 512, yfov_deg: float = 90.0, znear: float = 0.05,
                 zfar: float = 50.0):
        import pyrender

        from sonicverse_core.errors import ConfigError

        if not (16 <= width <= 8192 and 16 <= height <= 8192) or not (10 <= yfov_deg <= 170):
            raise ConfigError("view size must be 16-8192 pixels and the field of view 10-170 degrees")
        self.core, self.width, self.height = scene, width, height
        self.rs = RenderScene(scene)
        self.scene = self.rs.scene
        self.camera = pyrender.PerspectiveCamera(yfov=np.radians(yfov_deg), znear=znear, zfar=zfar,
                                                 aspectRatio=width / height)
        self.cam_node = self.scene.add(self.camera, pose=np.eye(4))
        self.renderer = pyrender.OffscreenRenderer(width, height)
        self._flags = pyrender.RenderFlags.NONE

    def sync(self) -> None:
        """Follow doors and moved objects when the core scene changed."""
        self.rs.sync()

    def render_eye(self, pose: np.ndarray, depth: bool = False):
        self.scene.set_pose(self.cam_node, pose)
        if depth:
            return self.renderer.render(self.scene, flags=self._flags)
        import pyrender

        return self.renderer.render(self.scene, flags=self._flags | pyrender.RenderFlags.SKIP_CULL_FACES)[0]

    def render_stereo(self, head, ipd: float = IPD) -> np.ndarray:
        """(2, height, width, 3) uint8: left and right eye for head (x, y, z, yaw[, pitch])."""
        self.sync()
        m = head_matrix(*head)
        out = np.empty((2, self.height, self.width, 3), np.uint8)
        for k, side in enumerate((-0.5, 0.5)):  # left eye: -0.5 along the camera's +x (right) axis
            e = m.copy()
            e[:3, 3] += side * ipd * m[:3, 0]
            out[k] = self.render_eye(e)
        return out

    def close(self) -> None:
        self.renderer.delete()
