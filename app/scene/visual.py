"""The visual scene built from the core scene: one pyrender scene, dynamic objects (doors, carried things) as nodes
whose poses follow the core scene, and a stereo camera rig. pyrender is imported here only (lazily by callers).

Offscreen rendering goes through EGL (PYOPENGL_PLATFORM=egl, set before the first OpenGL import): Mesa's llvmpipe
on a CPU, the GPU's driver where there is one. Create it inside the process (or worker) that renders.
"""
from __future__ import annotations

import os

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

IPD = 0.064  # m between the eyes (adult average)


def _palette(n: int) -> np.ndarray:
    """A fixed colour per acoustic material id (RGBA uint8), muted for walls, brighter for furniture."""
    rng = np.random.default_rng(7)
    c = rng.uniform(90, 230, (max(n, 1), 4)).astype(np.uint8)
    c[:, 3] = 255
    return c


def head_matrix(x, y, z, yaw, pitch=0.0) -> np.ndarray:
    """4x4 camera-to-world pose for a head at (x, y, z) with yaw/pitch in degrees (pyrender/OpenGL camera: looks
    along its -z, y up)."""
    a, p = np.radians(yaw), np.radians(pitch)
    fwd = np.array([np.cos(a) * np.cos(p), np.sin(a) * np.cos(p), np.sin(p)])
    left = np.array([-np.sin(a), np.cos(a), 0.0])
    up = np.cross(fwd, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = -left, up, -fwd, (x, y, z)
    return m


class VisualScene:
    """pyrender scene of a core scene; ``sync()`` copies dynamic poses, ``render_stereo(head)`` draws both eyes."""

    def __init__(self, scene, width: int = 512, height: int = 512, yfov_deg: float = 90.0, znear: float = 0.05,
                 zfar: float = 50.0):
        import pyrender
        import trimesh

        from sonicverse_core.errors import ConfigError
        from sonicverse_core.scene.materials import MATERIAL_INDEX

        if not (16 <= width <= 8192 and 16 <= height <= 8192) or not (10 <= yfov_deg <= 170):
            raise ConfigError("view size must be 16-8192 pixels and the field of view 10-170 degrees")
        self.core, self.width, self.height = scene, width, height
        pal = _palette(len(MATERIAL_INDEX))
        self.scene = pyrender.Scene(bg_color=(0.55, 0.6, 0.7, 1.0), ambient_light=(0.35, 0.35, 0.35))
        sm = scene.static_mesh()
        if len(sm):
            tm = trimesh.Trimesh(sm.vertices, sm.faces, face_colors=pal[sm.face_material], process=False)
            self.scene.add(pyrender.Mesh.from_trimesh(tm, smooth=False))
        self.nodes = {}
        for o in scene.objects:
            tm = o.mesh.copy()
            tm.visual.face_colors = pal[MATERIAL_INDEX[o.material]]
            self.nodes[o.name] = self.scene.add(pyrender.Mesh.from_trimesh(tm, smooth=False), pose=o.pose)
        self._version = scene.dynamic_version
        self.scene.add(pyrender.DirectionalLight(intensity=3.0), pose=head_matrix(0, 0, 0, 30, -60))
        self.camera = pyrender.PerspectiveCamera(yfov=np.radians(yfov_deg), znear=znear, zfar=zfar,
                                                 aspectRatio=width / height)
        self.cam_node = self.scene.add(self.camera, pose=np.eye(4))
        self.renderer = pyrender.OffscreenRenderer(width, height)
        self._flags = pyrender.RenderFlags.NONE

    def sync(self) -> None:
        """Copy the poses of dynamic objects (doors, moved objects) when the core scene changed."""
        if self.core.dynamic_version != self._version:
            for o in self.core.objects:
                self.scene.set_pose(self.nodes[o.name], o.pose)
            self._version = self.core.dynamic_version

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
