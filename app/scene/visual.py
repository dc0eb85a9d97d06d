"""The visual scene built from the core scene: one pyrender scene whose doors and moved objects follow the core
scene every frame, the user's avatar (head, body, hands) and the robots as bodies that robots' cameras see, and
eye / camera renders into offscreen framebuffers. Imported only when views are rendered (the audio-only mode and
the core never import it).

Offscreen rendering goes through EGL (PYOPENGL_PLATFORM=egl, set before the first OpenGL import): Mesa's llvmpipe
on a CPU, the GPU's driver where there is one. Create it inside the process (or worker) that renders.

Speed on a CPU (measured, see ``sonicverse bench vr``): pyrender's lit PBR shader costs ~5x a flat one on llvmpipe,
so by default the views draw the home's look (:mod:`sonicverse_core.scene.look`: textures, and light baked per
vertex once per home) with the FLAT shader; ``shading="pbr"`` lights the same textures per pixel with shadows (the
GPU path), ``"baked"`` is the flat look (a colour per face, a directional light baked in) and ``"lit"`` pyrender's
lit shader on it. Multisampling (pyrender always renders 4x MSAA) and the depth read-back that a display does not
need are optional. Both approximations are measured against the full path by ``bench vr`` (mean pixel error), and
the look against the flat look (frame rate).
"""
from __future__ import annotations

import numpy as np

from app.scene.eyes import IPD, eye_offsets
from sonicverse_core.errors import ConfigError
from sonicverse_core.scene.furniture import turtlebot
from sonicverse_core.scene.look import LIGHT_DIR, bake_lighting  # noqa: F401
from sonicverse_core.scene.model import yaw_pose
from sonicverse_core.sensors.camera import RenderScene, camera_matrix as head_matrix  # sets PYOPENGL_PLATFORM=egl
from sonicverse_core.sensors.offscreen import offscreen_renderer  # noqa: F401  (re-exported)

import pyrender  # noqa: E402

#: room culling: on llvmpipe one merged mesh is faster for small homes (bench vr: 0.79-0.85x at 1.3k triangles),
#: even at 85k (0.98-1.10x), and ahead at 338k (1.07x); a GPU, where memory is what culling saves, is not measured
CULL_MIN_TRIANGLES = 250_000
SKIN = (224, 172, 140, 255)
SHIRT = (60, 110, 190, 255)


class FixedCamera(pyrender.Camera):
    """A camera with a given OpenGL projection matrix (OpenVR hands one per eye, asymmetric)."""

    def __init__(self, projection: np.ndarray, znear: float = 0.05, zfar: float = 50.0):
        super().__init__(znear=znear, zfar=zfar)
        self.projection = np.asarray(projection, float)

    def get_projection_matrix(self, width=None, height=None):
        return self.projection


#: how views are shaded: 'home' (the home's look: textures and light baked per vertex, FLAT shader; the CPU
#: default), 'pbr' (the same textures lit per pixel by the rooms' lamps and the sun with shadows; for a GPU),
#: 'baked' (one colour per face, a directional light baked in), 'lit' (one colour per face, pyrender's lit shader)
SHADINGS = ("home", "pbr", "baked", "lit")

AVATAR_HEIGHT = 1.75
AVATAR_NECK = 0.82 * AVATAR_HEIGHT + 0.06  # the top of the body's neck (furniture.person)


def _avatar_body() -> tuple:
    """The user's body below the tracked head, without the hands (tracked too): the person's parts."""
    from sonicverse_core.scene.furniture import person

    return tuple(p for p in person(AVATAR_HEIGHT, 0.25, shirt=SHIRT) if p.name not in ("head", "hair", "nose", "hand"))


def _parts_mesh(parts) -> "pyrender.Mesh":
    """One mesh of parts (ObjectPart) in their colours, lit as the rest of the scene."""
    import trimesh

    tm = trimesh.util.concatenate([p.mesh for p in parts])
    cols = np.concatenate([np.tile(np.asarray(p.colour, np.uint8), (len(p.mesh.faces), 1)) for p in parts])
    tm.visual.face_colors = bake_lighting(cols, tm.face_normals)
    return pyrender.Mesh.from_trimesh(tm, smooth=False)


def _solid(tm, colour) -> "pyrender.Mesh":
    tm.visual.face_colors = bake_lighting(np.tile(np.array(colour, np.uint8), (len(tm.faces), 1)), tm.face_normals)
    return pyrender.Mesh.from_trimesh(tm, smooth=False)


class VisualScene:
    """pyrender scene of a core scene with an avatar and robots. ``render_eye(pose, projection)`` draws one view;
    ``render_stereo(head)`` both eyes of a head at (x, y, z, yaw[, pitch]); ``render_camera(pose)`` a robot's
    view (with the avatar's head and body visible). ``cull_rooms``: each view loads and draws only the rooms visible
    from where its camera stands (:mod:`sonicverse_core.scene.visibility`); 'auto': in scenes of
    ``CULL_MIN_TRIANGLES`` or more, below which one merged mesh draws faster on a CPU."""

    def __init__(self, scene, width: int = 512, height: int = 512, yfov_deg: float = 90.0, znear: float = 0.05,
                 zfar: float = 50.0, shading: str = "home", msaa: bool = True, robots: int = 0,
                 avatar: bool = True, cull_rooms: bool | str = "auto", texture_filter: str | None = None):
        if not (16 <= width <= 8192 and 16 <= height <= 8192) or not (10 <= yfov_deg <= 170):
            raise ConfigError("view size must be 16-8192 pixels and the field of view 10-170 degrees")
        if shading not in SHADINGS:
            raise ConfigError(f"shading must be one of {', '.join(SHADINGS)}, got '{shading}'")
        import trimesh

        self.core, self.width, self.height, self.shading = scene, width, height, shading
        # only the rooms a viewer may see are loaded and drawn (sonicverse_core.scene.visibility)
        self.visibility = None
        if cull_rooms not in ("auto", True, False):
            raise ConfigError(f"cull_rooms must be True, False or 'auto', got {cull_rooms!r}")
        if cull_rooms == "auto":
            cull_rooms = scene.triangle_count >= CULL_MIN_TRIANGLES
        if cull_rooms and len(scene.rooms) > 1:
            from sonicverse_core.scene.visibility import RoomVisibility

            self.visibility = RoomVisibility(scene)
        self.rs = RenderScene(scene, face_shading=bake_lighting if shading == "baked" else None,
                              rooms=self.visibility is not None,
                              look=shading if shading in ("home", "pbr") else "flat", texture_filter=texture_filter)
        self.scene = self.rs.scene
        self.znear, self.zfar = znear, zfar
        self.camera = pyrender.PerspectiveCamera(yfov=np.radians(yfov_deg), znear=znear, zfar=zfar,
                                                 aspectRatio=width / height)
        self.cam_node = self.scene.add(self.camera, pose=np.eye(4))
        self.renderer = offscreen_renderer(width, height, msaa=msaa, colour_only=True)
        if shading == "pbr":
            from sonicverse_core.sensors.offscreen import use_pbr_shaders

            use_pbr_shaders(self.renderer)
        self._flags = pyrender.RenderFlags.FLAT if shading in ("home", "baked") else \
            self.rs.flags if shading == "pbr" else pyrender.RenderFlags.SKIP_CULL_FACES
        self._fixed: dict[bytes, FixedCamera] = {}
        self.avatar = {}
        if avatar:  # head, body (hidden in the user's own eyes), two hands
            self.avatar["head"] = self.scene.add(_solid(trimesh.creation.icosphere(2, 0.11), SKIN))
            self.avatar["body"] = self.scene.add(_parts_mesh(_avatar_body()))
            for k in ("left", "right"):
                self.avatar[k] = self.scene.add(_solid(trimesh.creation.icosphere(1, 0.05), SKIN))
        self.robot_nodes = [self.scene.add(_parts_mesh(turtlebot())) for _ in range(robots)]
        self._robot_cam = None

    # --- per frame ----------------------------------------------------------------------------------------------
    def sync(self, head: np.ndarray | None = None, hands=None, hands_valid=None, robots=()) -> None:
        """Follow doors and moved objects; place the avatar (head 4x4, hands (2, 4, 4)) and robots (x, y, yaw)."""
        self.rs.sync()
        if head is not None and self.avatar:
            self.scene.set_pose(self.avatar["head"], head)
            z0 = self.core.floor_z
            top = max(head[2, 3] - 0.12, z0 + 0.3)  # the neck's top, under the tracked head
            yaw = np.arctan2(-head[1, 2], -head[0, 2])  # the body turns with the head (forward: -z)
            body = np.eye(4)
            body[:3, :3] = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]) @ \
                np.diag([1.0, 1.0, (top - z0) / AVATAR_NECK])
            body[:3, 3] = (head[0, 3], head[1, 3], z0)
            self.scene.set_pose(self.avatar["body"], body)
            for k, name in enumerate(("left", "right")):
                ok = hands is not None and (hands_valid is None or hands_valid[k])
                self.avatar[name].mesh.is_visible = bool(ok)
                if ok:
                    self.scene.set_pose(self.avatar[name], hands[k])
        for node, rb in zip(self.robot_nodes, robots):
            self.scene.set_pose(node, yaw_pose(rb[0], rb[1], self.core.floor_z, rb[2]))

    def _cull(self, pose: np.ndarray) -> None:
        """Load and draw only the rooms visible from where this view's camera stands."""
        if self.visibility is not None:
            self.rs.show(self.visibility.visible_from(pose[:2, 3]))

    def _own_body(self, visible: bool) -> None:
        for k in ("head", "body"):
            if k in self.avatar:
                self.avatar[k].mesh.is_visible = visible

    def render_eye(self, pose: np.ndarray, projection: np.ndarray | None = None) -> np.ndarray:
        """(H, W, 3) uint8 seen from a camera-frame pose; ``projection`` (4x4) overrides the symmetric one."""
        if projection is None:
            cam = self.camera
        else:
            key = np.asarray(projection, np.float64).tobytes()
            cam = self._fixed.get(key)
            if cam is None:
                cam = self._fixed[key] = FixedCamera(projection, self.znear, self.zfar)
        if self.cam_node.camera is not cam:
            self.cam_node.camera = cam
        self.scene.set_pose(self.cam_node, pose)
        self._cull(pose)
        self.rs.place_lights(pose[:2, 3])
        self._own_body(False)
        try:
            return self.renderer.render(self.scene, flags=self._flags)[0]
        finally:
            self._own_body(True)

    def render_views(self, head: np.ndarray, eye_to_head, projections=None, out: np.ndarray | None = None):
        """(n_eyes, H, W, 3) uint8 for a head pose (4x4) and per-eye eye->head transforms (and projections)."""
        n = len(eye_to_head)
        out = np.empty((n, self.height, self.width, 3), np.uint8) if out is None else out
        for k in range(n):
            out[k] = self.render_eye(head @ eye_to_head[k], None if projections is None else projections[k])
        return out

    def render_stereo(self, head, ipd: float = IPD) -> np.ndarray:
        """(2, height, width, 3) uint8: left and right eye for head (x, y, z, yaw[, pitch])."""
        self.sync()
        return self.render_views(head_matrix(*head), eye_offsets(ipd))

    def render_camera(self, pose: np.ndarray, width: int = 128, height: int = 128,
                      hfov_deg: float = 90.0, depth: bool = False):
        """(H, W, 3) uint8 seen by a robot's camera (camera-frame pose); the avatar is visible. Drawn by the same
        GL context as the eyes (pyrender binds a mesh to one context), at its own viewport size. With ``depth``:
        (rgb, depth (H, W) float32 m along the optical axis, 0 where nothing is hit)."""
        key = (width, height, hfov_deg)
        if self._robot_cam is None or self._robot_cam[0] != key:
            yfov = 2 * np.arctan(np.tan(np.radians(hfov_deg) / 2) * height / width)
            self._robot_cam = (key, pyrender.PerspectiveCamera(yfov=yfov, znear=0.05, zfar=self.zfar,
                                                               aspectRatio=width / height))
        self.cam_node.camera = self._robot_cam[1]
        self.scene.set_pose(self.cam_node, pose)
        self._cull(pose)
        r = self.renderer
        r.viewport_width, r.viewport_height = width, height
        inner = r._renderer
        reader = inner.__dict__.get("_read_main_framebuffer")
        if depth and reader is not None:  # the eyes skip the depth read-back; the robot's depth camera needs it
            del inner._read_main_framebuffer
        try:
            out = r.render(self.scene, flags=self._flags)
            return (out[0], np.asarray(out[1], np.float32)) if depth else out[0]
        finally:
            if depth and reader is not None:
                inner._read_main_framebuffer = reader
            r.viewport_width, r.viewport_height = self.width, self.height

    def close(self) -> None:
        if self.renderer is not None:
            from sonicverse_core.sensors.offscreen import release_offscreen

            release_offscreen(self.renderer)
            self.renderer = None
