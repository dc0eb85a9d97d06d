"""RGB and depth cameras rendered offscreen with pyrender (EGL: Mesa llvmpipe on a CPU, the GPU's driver where
there is one). This module is imported only when a camera is asked for; create cameras inside the process that
renders (vector-env workers create their own).

Depth is metric (m along the optical axis). Like a real structured-light / ToF camera, pixels nearer than
``depth_min`` or farther than ``depth_max`` read 0 (invalid). The TurtleBot's camera: 0.8-3.5 m (sim-to-real).
"""
from __future__ import annotations

import os

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from sonicverse_core.errors import ConfigError  # noqa: E402
from sonicverse_core.sensors.offscreen import offscreen_renderer, release_offscreen, use_pbr_shaders  # noqa: E402
from sonicverse_core.scene.look import STRUCTURE_COLOURS, palette, part_category  # noqa: E402,F401


def camera_matrix(x, y, z, yaw, pitch=0.0) -> np.ndarray:
    """4x4 camera-to-world pose for an eye at (x, y, z) with yaw/pitch in degrees (an OpenGL camera looks along its
    -z with y up)."""
    a, p = np.radians(yaw), np.radians(pitch)
    fwd = np.array([np.cos(a) * np.cos(p), np.sin(a) * np.cos(p), np.sin(p)])
    left = np.array([-np.sin(a), np.cos(a), 0.0])
    up = np.cross(fwd, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = -left, up, -fwd, (x, y, z)
    return m


def id_colour(i) -> np.ndarray:
    """Instance id(s) -> RGBA uint8 (24 bits of id in R, G, B; alpha 255); 0 is nothing."""
    i = np.asarray(i, np.int64)
    return np.stack([i & 255, (i >> 8) & 255, (i >> 16) & 255, np.full_like(i, 255)], -1).astype(np.uint8)


def decode_ids(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 of an id render -> (H, W) int32 instance ids."""
    c = rgb.astype(np.int32)
    return c[..., 0] | (c[..., 1] << 8) | (c[..., 2] << 16)


#: looks of a render scene: 'home' (textures, light baked per vertex, FLAT shader: the CPU path), 'pbr' (textures,
#: pyrender's lit PBR shader with the rooms' lamps and the sun casting shadows: the GPU path), 'flat' (a colour per
#: face, pyrender's directional light or a baked one)
LOOKS = ("home", "pbr", "flat")
PBR_LAMP, PBR_SUN, PBR_AMBIENT = 14.0, 2.0, 0.25
UNTEXTURED = ("plaster", "plain")

#: category ids the same in every scene (an agent learns them once): 0 is nothing; a scene's other categories
#: (a mesh scene's part names) follow in sorted order, and an actor's new category after them
CLASSES = ("", "wall", "floor", "ceiling", "window", "door", "threshold", "person", "robot",
           "straight_chair", "breakfast_table", "picture", "bottom_cabinet", "cushion", "sofa", "bed", "shelf",
           "sink", "toilet", "stool", "standing_tv", "shower", "bathtub", "countertop")


class SemanticLabels:
    """Instance and category ids of a scene's semantic camera. Instances: 0 nothing, 1..N the scene's objects (in
    order), then the static structure's parts, then actors (bodies not in the scene, e.g. the person) as they are
    added. Categories: :data:`CLASSES` first (fixed ids), then the scene's other categories in sorted order;
    ``categories[k]`` names category k, ``instances[i]`` is (name, category) of instance i."""

    def __init__(self, scene):
        sm = scene.static_mesh()
        self.instances = [("", "")] + [(o.name, o.category) for o in scene.objects] + \
            [(p, part_category(p)) for p in sm.part_names]
        self.categories = list(CLASSES) + sorted({c for _, c in self.instances[1:]} - set(CLASSES))
        self._refresh()

    def _refresh(self) -> None:
        for _, c in self.instances[1:]:  # a new category (an actor's) is appended: the others keep their ids
            if c not in self.categories:
                self.categories.append(c)
        idx = {c: k for k, c in enumerate(self.categories)}
        self.lut = np.array([idx[c] for _, c in self.instances], np.int32)

    def add_actor(self, name: str, category: str) -> int:
        for i, (n, _) in enumerate(self.instances):
            if n == name and i > 0:
                return i
        self.instances.append((name, category))
        self._refresh()
        return len(self.instances) - 1

    def category_id(self, name: str) -> int:
        return self.categories.index(name)


class RenderScene:
    """The pyrender scene of a core scene, drawn in as few primitives as possible (pyrender spends ~0.3 ms of
    Python per primitive and frame): the static structure and every object still at its initial pose are one
    merged mesh; an object gets a node of its own the first time it moves (a door swinging, a carried cushion),
    and the merged mesh is rebuilt without it. ``look``: 'home' (the home's baked look: textures and light per
    vertex, drawn with the FLAT shader), 'pbr' (the same textures lit per pixel by the nearest rooms' lamps and the
    sun with shadows) or 'flat' (static parts coloured by material, objects by their parts' colours or semantic
    category, lit by pyrender or by ``face_shading``). ``sync()`` follows the core scene's dynamic state."""

    #: a room's mesh leaves the GL context after this many ``show`` calls without it (hysteresis: a viewer on a
    #: threshold, or an eye and a robot camera in different rooms, do not upload it again every frame)
    UNLOAD_AFTER = 90

    def __init__(self, scene, bg=(0.55, 0.6, 0.7, 1.0), merge: bool = True, face_shading=None,
                 rooms: bool = False, ids: bool = False, look: str = "flat", texture_filter: str | None = None):
        import pyrender

        from sonicverse_core.scene.materials import MATERIAL_INDEX

        if look not in LOOKS:
            raise ConfigError(f"look must be one of {', '.join(LOOKS)}, got '{look}'")
        self.core = scene
        self.merge = merge
        # ids: every face coloured by its instance id (24 bits in RGB) for the semantic camera, drawn unlit
        self.ids = ids
        if ids:
            bg = (0.0, 0.0, 0.0, 1.0)
            face_shading = None
            look = "flat"
        # look 'home': textured, light baked per vertex (sonicverse_core.scene.look), drawn with the FLAT shader;
        # 'flat': one colour per face, lit by pyrender (or by ``face_shading``)
        self.look = look
        self.home = None
        self._atlas_mat = self._plain_mat = None  # made on first use, shared by this scene's primitives
        # the atlas' minification filter: 'bilinear' (within the nearest mip level; the CPU path: trilinear costs
        # ~1.5x the frame time at 2 x 512^2 on llvmpipe, `bench vr`) or 'trilinear' (between levels; the GPU path)
        self.texture_filter = texture_filter or ("trilinear" if look == "pbr" else "bilinear")
        if self.texture_filter not in ("bilinear", "trilinear"):
            raise ConfigError(f"texture_filter must be 'bilinear' or 'trilinear', got '{texture_filter}'")
        if look in ("home", "pbr"):
            from sonicverse_core.scene.look import home_look

            self.home = home_look(scene)
            bg = (0.62, 0.72, 0.86, 1.0)
        # the merged mesh split by room (``show`` loads what a viewer may see); one group (None) otherwise
        if rooms and scene.rooms:
            from sonicverse_core.scene.visibility import object_room, room_faces

            self._groups = {g: f for g, f in room_faces(scene).items() if len(f) or g is None}
            self._obj_group = {o.name: object_room(scene, o) for o in scene.objects}
        else:
            self._groups = {None: np.arange(len(scene.static_mesh()))}
            self._obj_group = {o.name: None for o in scene.objects}
        if self.home is not None:
            self._groups.setdefault(None, np.zeros(0, np.int64))  # the trim's group
        self.group_nodes: dict = {}  # group -> its node (in the pyrender scene only while loaded)
        self._last_use: dict = {}
        self._shows = 0
        self._shade = face_shading  # (colours (n, 4), normals (n, 3)) -> colours: lighting baked into the faces
        self.scene = pyrender.Scene(bg_color=bg, ambient_light=(0.35, 0.35, 0.35))
        self._mat_pal = palette(len(MATERIAL_INDEX))
        cats = sorted({o.category for o in scene.objects})
        cpal = palette(len(cats), seed=11)
        self._obj_colour = {o.name: cpal[cats.index(o.category)] for o in scene.objects}
        if ids:
            self._obj_colour = {o.name: id_colour(i + 1) for i, o in enumerate(scene.objects)}
        self._rest = {o.name: o.pose.copy() for o in scene.objects}
        self.nodes: dict = {}  # object name -> node of its own
        self._local: dict = {}  # object name -> (its first part's mesh, all its parts as one local mesh)
        self._batched: set[str] = set()
        own = [] if merge else [o.name for o in scene.objects]
        self._build_batch(exclude=set(own))
        for name in own:
            self._own_node(name)
        if not ids and look == "flat":
            self.scene.add(pyrender.DirectionalLight(intensity=3.0), pose=camera_matrix(0, 0, 0, 30, -60))
        self.lamp_nodes: list = []
        if look == "pbr":  # lit per pixel: the rooms' lamps (the nearest MAX_N_LIGHTS) and the sun, with shadows
            from pyrender.constants import MAX_N_LIGHTS

            from sonicverse_core.scene.look import LIGHT_DIR, lamps

            self.scene.ambient_light = np.full(3, PBR_AMBIENT)
            self._lamps = lamps(scene)
            for p in self._lamps[:MAX_N_LIGHTS]:
                pose = np.eye(4)
                pose[:3, 3] = p
                self.lamp_nodes.append(self.scene.add(pyrender.SpotLight(
                    color=(1.0, 0.9, 0.75), intensity=PBR_LAMP, innerConeAngle=0.7, outerConeAngle=1.45), pose=pose))
            d = -LIGHT_DIR / np.linalg.norm(LIGHT_DIR)
            self.scene.add(pyrender.DirectionalLight(color=(1.0, 0.97, 0.9), intensity=PBR_SUN),
                           pose=camera_matrix(0, 0, 0, np.degrees(np.arctan2(d[1], d[0])),
                                              np.degrees(np.arcsin(d[2]))))
        self._version = scene.dynamic_version

    def place_lights(self, xy) -> None:
        """Lit path: the lamp nodes (pyrender draws at most MAX_N_LIGHTS spot lights) at the lamps nearest ``xy``."""
        if not self.lamp_nodes:
            return
        order = np.argsort(np.linalg.norm(self._lamps[:, :2] - np.asarray(xy, float)[:2], axis=1))
        for node, k in zip(self.lamp_nodes, order):
            pose = np.eye(4)
            pose[:3, 3] = self._lamps[k]
            self.scene.set_pose(node, pose)

    @property
    def flags(self):
        """The pyrender flags this scene is drawn with (colour and depth)."""
        import pyrender

        F = pyrender.RenderFlags
        if self.look == "pbr":
            return F.SHADOWS_SPOT | F.SHADOWS_DIRECTIONAL
        return F.FLAT if (self.look == "home" or self.ids) else F.NONE

    def _atlas_material(self):
        """One material with the home's texture atlas (mipmapped), shared by every primitive of this scene."""
        if self._atlas_mat is None:
            import pyrender
            from pyrender.constants import GLTF

            from sonicverse_core.scene.look import atlas

            img, _ = atlas()
            tex = pyrender.Texture(source=img, source_channels="RGBA",
                                   sampler=pyrender.Sampler(magFilter=GLTF.LINEAR,
                                                            minFilter=GLTF.LINEAR_MIPMAP_LINEAR
                                                            if self.texture_filter == "trilinear"
                                                            else GLTF.LINEAR_MIPMAP_NEAREST,
                                                            wrapS=GLTF.CLAMP_TO_EDGE, wrapT=GLTF.CLAMP_TO_EDGE))
            self._atlas_mat = pyrender.MetallicRoughnessMaterial(baseColorTexture=tex, alphaMode="OPAQUE",
                                                                 metallicFactor=0.0, roughnessFactor=0.85)
        return self._atlas_mat

    def _home_mesh(self, parts: list) -> "object":
        """One pyrender mesh (one primitive) of look arrays (dicts of pos, nrm, uv, col)."""
        import pyrender
        from pyrender.constants import GLTF

        colour = "alb" if self.look == "pbr" else "col"
        cat = {k: np.concatenate([p[k] for p in parts]) for k in ("pos", "nrm", "uv", colour)}
        plain = self._untextured(cat["uv"])
        prims = []
        for sel, mat in ((~plain, self._atlas_material()), (plain, self._plain_material())):
            if sel.any():
                prims.append(pyrender.Primitive(positions=cat["pos"][sel], normals=cat["nrm"][sel],
                                                texcoord_0=cat["uv"][sel], color_0=cat[colour][sel], material=mat,
                                                mode=GLTF.TRIANGLES))
        return pyrender.Mesh(primitives=prims)

    def _untextured(self, uv: np.ndarray) -> np.ndarray:
        """Per-vertex mask of the triangles drawn without the texture (CPU path: painted plaster and plain parts,
        whose tiles are near-uniform; sampling costs more than a primitive more)."""
        from sonicverse_core.scene.look import atlas

        n = len(uv)
        if self.look == "pbr" or not UNTEXTURED:
            return np.zeros(n, bool)
        _, rects = atlas()
        c = uv.reshape(-1, 3, 2).mean(1)
        out = np.zeros(len(c), bool)
        for kind in UNTEXTURED:
            u0, v0, u1, v1 = rects[kind]
            out |= (c[:, 0] >= u0) & (c[:, 0] <= u1) & (c[:, 1] >= v0) & (c[:, 1] <= v1)
        return np.repeat(out, 3)

    def _plain_material(self):
        if self._plain_mat is None:
            import pyrender

            from sonicverse_core.scene.look import TEXTURE_MEAN

            self._plain_mat = pyrender.MetallicRoughnessMaterial(
                baseColorFactor=(TEXTURE_MEAN, TEXTURE_MEAN, TEXTURE_MEAN, 1.0), alphaMode="OPAQUE",
                metallicFactor=0.0, roughnessFactor=0.85)
        return self._plain_mat

    def _home_group(self, fidx: np.ndarray, objects: list, trim: bool) -> tuple:
        """(mesh, triangles) of a group in the home look: its static faces, objects at rest, and with ``trim`` the
        home's trim (drawn with the common group)."""
        st = self.home.static
        parts = []
        if len(fidx) or trim:
            keep = np.isin(st["face"], fidx) | ((st["face"] < 0) & trim)
            v = np.repeat(keep, 3)
            parts.append({k: st[k][v] for k in ("pos", "nrm", "uv", "col", "alb")})
        for o in objects:
            a = self.home.objects[o.name]
            R, t = o.pose[:3, :3].astype(np.float32), o.pose[:3, 3].astype(np.float32)
            parts.append({"pos": a["pos"] @ R.T + t, "nrm": a["nrm"] @ R.T, "uv": a["uv"], "col": a["col"],
                          "alb": a["alb"]})
        parts = [p for p in parts if len(p["pos"])]
        if not parts:
            return None, 0
        return self._home_mesh(parts), sum(len(p["pos"]) for p in parts) // 3

    def _build_batch(self, exclude: set) -> None:
        """One mesh per group: its static faces and the objects at rest in it (all but ``exclude``)."""
        import pyrender
        import trimesh

        loaded = {g for g, node in self.group_nodes.items() if self.scene.has_node(node)}
        for node in self.group_nodes.values():
            if self.scene.has_node(node):
                self.scene.remove_node(node)
        sm = self.core.static_mesh()
        self._batched = {o.name for o in self.core.objects if o.name not in exclude}
        self.group_nodes = {}
        self.group_triangles = {}
        for g, fidx in self._groups.items():
            if self.home is not None:
                mesh, ntri = self._home_group(fidx, [o for o in self.core.objects if o.name in self._batched
                                                     and self._obj_group[o.name] == g], trim=g is None)
                if mesh is None:
                    continue
                node = pyrender.Node(mesh=mesh)
                self.group_nodes[g] = node
                self.group_triangles[g] = ntri
                if g is None or g in loaded:
                    self.scene.add_node(node)
                continue
            verts, faces, cols, off = [], [], [], 0
            if len(fidx):
                used, inv = np.unique(sm.faces[fidx], return_inverse=True)
                verts.append(sm.vertices[used])
                faces.append(inv.reshape(-1, 3))
                cols.append(id_colour(len(self.core.objects) + 1 + sm.face_part[fidx]) if self.ids
                            else self._static_colours()[fidx])
                off = len(used)
            for o in self.core.objects:
                if o.name in self._batched and self._obj_group[o.name] == g:
                    m, c = self._object_mesh(o)
                    verts.append(m.vertices @ o.pose[:3, :3].T + o.pose[:3, 3])
                    faces.append(m.faces + off)
                    cols.append(c)
                    off += len(m.vertices)
            if not faces:
                continue
            tm = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=False)
            tm.visual.face_colors = self._colours(np.concatenate(cols), tm.face_normals)
            node = pyrender.Node(mesh=pyrender.Mesh.from_trimesh(tm, smooth=False))
            self.group_nodes[g] = node
            self.group_triangles[g] = len(tm.faces)
            if g is None or g in loaded:  # a room's mesh is added by the first show() that needs it
                self.scene.add_node(node)

    def show(self, rooms=None) -> None:
        """Draw only the groups of these rooms (None: all) until the next call: a room's mesh is loaded into the
        GL context the first time it is needed and unloaded after ``UNLOAD_AFTER`` calls without it."""
        want = set(self.group_nodes) if rooms is None else (set(rooms) | {None}) & set(self.group_nodes)
        for g, node in self.group_nodes.items():
            if g in want:
                self._last_use[g] = self._shows
                if not self.scene.has_node(node):
                    self.scene.add_node(node)
                node.mesh.is_visible = True
            elif self.scene.has_node(node):
                node.mesh.is_visible = False
                if self._shows - self._last_use.get(g, -1) > self.UNLOAD_AFTER:
                    self.scene.remove_node(node)  # pyrender frees its buffers at the next render
        self._shows += 1

    @property
    def drawn_triangles(self) -> int:
        """Triangles of the merged groups the last ``show`` draws."""
        return sum(self.group_triangles[g] for g, n in self.group_nodes.items()
                   if self.scene.has_node(n) and n.mesh.is_visible)

    @property
    def loaded_triangles(self) -> int:
        """Triangles of the merged groups now in the GL context (objects with nodes of their own not counted)."""
        return sum(self.group_triangles[g] for g, n in self.group_nodes.items() if self.scene.has_node(n))

    def _static_colours(self) -> np.ndarray:
        """(faces, 4) colours of the static structure: walls painted, ceilings white, wooden floors, sky-blue
        windows (by the part's category, :data:`STRUCTURE_COLOURS`); other parts by their material."""
        if getattr(self, "_static_cols", None) is None:
            sm = self.core.static_mesh()
            per_part = np.array([STRUCTURE_COLOURS.get(part_category(n), (0, 0, 0, 0)) for n in sm.part_names]
                                or np.zeros((0, 4)), np.uint8).reshape(-1, 4)
            cols = self._mat_pal[sm.face_material].copy()
            known = per_part[sm.face_part, 3] > 0
            cols[known] = per_part[sm.face_part[known]]
            self._static_cols = cols
        return self._static_cols

    def _object_mesh(self, o) -> tuple:
        """(local mesh of all its parts, (faces, 4) uint8 colours): each part in its own colour (the category's
        colour for an object without parts; its instance id in an id scene)."""
        import trimesh

        looks = o.looks()
        hit = self._local.get(o.name)
        if hit is None or hit[0] is not looks[0][2]:  # parts are made once: concatenated once
            meshes = [m for _, _, m, _ in looks]
            hit = self._local[o.name] = (looks[0][2], meshes[0] if len(meshes) == 1 else
                                         trimesh.util.concatenate(meshes))
        mesh = hit[1]
        if self.ids:
            cols = np.tile(self._obj_colour[o.name], (len(mesh.faces), 1))
        else:
            cols = np.concatenate([np.tile(np.asarray(c if c is not None else self._obj_colour[o.name], np.uint8),
                                           (len(m.faces), 1)) for _, _, m, c in looks])
        return mesh, cols

    def _own_node(self, name: str) -> None:
        import pyrender
        import trimesh

        o = self.core.object(name)
        if self.home is not None:
            self.nodes[name] = self.scene.add(self._home_mesh([self.home.objects[name]]), pose=o.pose)
            return
        m, cols = self._object_mesh(o)
        tm = trimesh.Trimesh(m.vertices.copy(), m.faces.copy(), process=False)
        tm.visual.face_colors = self._colours(cols, tm.face_normals)
        self.nodes[name] = self.scene.add(pyrender.Mesh.from_trimesh(tm, smooth=False), pose=o.pose)

    def _colours(self, colours: np.ndarray, normals: np.ndarray) -> np.ndarray:
        return colours if self._shade is None else self._shade(colours, normals)

    def sync(self) -> None:
        if self.core.dynamic_version == self._version:
            return
        moved = [o.name for o in self.core.objects
                 if o.name in self._batched and not np.array_equal(o.pose, self._rest[o.name])]
        if moved:
            self._build_batch(exclude=set(self.nodes) | set(moved))
            for name in moved:
                self._own_node(name)
        for name, node in self.nodes.items():
            self.scene.set_pose(node, self.core.object(name).pose)
        self._version = self.core.dynamic_version


class RGBDCamera:
    """A pinhole camera in a core scene. ``render(x, y, z, yaw)`` -> {'rgb': (H, W, 3) uint8, 'depth': (H, W)
    float32 m, and with ``semantic``: 'semantic' (H, W) int32 category ids and 'instance' (H, W) int32 instance
    ids (``labels``: :class:`SemanticLabels`)}; only the images asked for are rendered (depth-only is about twice
    as fast; the semantic images are one more unlit pass over a twin scene coloured by instance id, in a GL context
    of its own). RGB is drawn in ``look`` (:data:`LOOKS`; default the home's baked look, the VR views' too), single-
    sampled unless ``msaa``."""

    def __init__(self, scene, width: int = 128, height: int = 128, hfov_deg: float = 90.0, depth_min: float = 0.0,
                 depth_max: float = 10.0, rgb: bool = True, depth: bool = True, semantic: bool = False,
                 look: str = "home", msaa: bool = False):
        if not (8 <= width <= 4096 and 8 <= height <= 4096):
            raise ConfigError(f"camera size must be 8-4096 pixels, got {width}x{height}")
        if not (10 <= hfov_deg <= 170):
            raise ConfigError(f"camera field of view must be 10-170 degrees, got {hfov_deg}")
        if not (0 <= depth_min < depth_max <= 100):
            raise ConfigError(f"need 0 <= depth_min < depth_max <= 100 m, got {depth_min}, {depth_max}")
        if not (rgb or depth or semantic):
            raise ConfigError("a camera needs rgb, depth or semantic")
        if look not in LOOKS:
            raise ConfigError(f"camera look must be one of {', '.join(LOOKS)}, got '{look}'")
        self.look = look
        import pyrender

        self.width, self.height = width, height
        self.want_rgb, self.want_depth, self.want_semantic = rgb, depth, semantic
        self.depth_min, self.depth_max = float(depth_min), float(depth_max)
        yfov = 2 * np.arctan(np.tan(np.radians(hfov_deg) / 2) * height / width)
        self.camera = pyrender.PerspectiveCamera(yfov=yfov, znear=0.05, zfar=max(50.0, depth_max * 1.5),
                                                 aspectRatio=width / height)
        # single-sampled by default, as embodied-AI cameras are (4x MSAA costs ~15% at 128^2 on llvmpipe)
        self.renderer = offscreen_renderer(width, height, msaa=msaa)
        if look == "pbr":
            use_pbr_shaders(self.renderer)
        # the semantic pass has a context of its own: one renderer drawing two scenes in turn uploads both every frame
        self.ids_renderer = offscreen_renderer(width, height, msaa=False) if semantic else None
        self._flags = pyrender.RenderFlags.DEPTH_ONLY
        self.core = None
        self.set_scene(scene)

    def set_scene(self, scene) -> None:
        """Build the render scene of another core scene (a new home); the GL context is kept."""
        if scene is self.core:
            return
        self.core = scene
        # depth alone needs no look (nothing is baked for a depth-only camera)
        self.rs = RenderScene(scene, look=self.look if self.want_rgb else "flat")
        self.scene = self.rs.scene
        if self.want_rgb:
            self._flags = self.rs.flags
        self.cam_node = self.scene.add(self.camera, pose=np.eye(4))
        self._actors: dict[str, tuple] = {}
        self.ids_rs = self.labels = None
        if self.want_semantic:
            self.ids_rs = RenderScene(scene, ids=True)
            self.labels = SemanticLabels(scene)
            self.ids_cam = self.ids_rs.scene.add(self.camera, pose=np.eye(4))

    # --- actors: bodies that are not part of the core scene (a person), seen but not heard as geometry ------------
    def set_actor(self, name: str, mesh, rgba=None, category: str | None = None) -> None:
        """Show ``mesh`` (a trimesh in its local frame) as actor ``name`` (the same mesh again: nothing to do) in
        ``rgba`` (None: the mesh's own face colours, else a skin tone); its semantic category is ``category``
        (default: its name without trailing numbers)."""
        import pyrender

        held = self._actors.get(name)
        if held is not None and held[0] is mesh:
            return
        if held is not None:
            self._remove_actor(held)
        tm = mesh.copy()
        if rgba is not None or getattr(mesh.visual, "kind", None) != "face":
            tm.visual.face_colors = np.tile(np.asarray(rgba or (200, 120, 90, 255), np.uint8), (len(tm.faces), 1))
        if self.rs.look == "home":  # the FLAT shader draws colours as they are: light them as the home's bodies
            from sonicverse_core.scene.look import bake_lighting

            tm.visual.face_colors = bake_lighting(np.asarray(tm.visual.face_colors, np.uint8), tm.face_normals)
        nodes = [self.scene.add(pyrender.Mesh.from_trimesh(tm, smooth=False), pose=np.eye(4))]
        if self.ids_rs is not None:
            i = self.labels.add_actor(name, category or part_category(name))
            tid = mesh.copy()
            tid.visual.face_colors = np.tile(id_colour(i), (len(tid.faces), 1))
            nodes.append(self.ids_rs.scene.add(pyrender.Mesh.from_trimesh(tid, smooth=False), pose=np.eye(4)))
        self._actors[name] = (mesh, nodes)

    def _remove_actor(self, held) -> None:
        self.scene.remove_node(held[1][0])
        if len(held[1]) > 1:
            self.ids_rs.scene.remove_node(held[1][1])

    def move_actor(self, name: str, pose: np.ndarray) -> None:
        nodes = self._actors[name][1]
        self.scene.set_pose(nodes[0], np.asarray(pose, float))
        if len(nodes) > 1:
            self.ids_rs.scene.set_pose(nodes[1], np.asarray(pose, float))

    def clear_actors(self) -> None:
        for held in self._actors.values():
            self._remove_actor(held)
        self._actors = {}

    def render(self, x, y, z, yaw, pitch=0.0) -> dict:
        import pyrender

        out = {}
        pose = camera_matrix(x, y, z, yaw, pitch)
        if self.want_rgb or self.want_depth:
            self.rs.sync()
            self.rs.place_lights((x, y))
            self.scene.set_pose(self.cam_node, pose)
            res = self.renderer.render(self.scene, flags=self._flags)
            if self.want_rgb:
                color, depth = res
                out["rgb"] = np.ascontiguousarray(color[..., :3])
            else:
                depth = res
            if self.want_depth:
                d = np.asarray(depth, np.float32)
                d = np.where((d < self.depth_min) | (d > self.depth_max), np.float32(0), d)
                out["depth"] = d
        if self.want_semantic:
            self.ids_rs.sync()
            self.ids_rs.scene.set_pose(self.ids_cam, pose)
            color, _ = self.ids_renderer.render(self.ids_rs.scene, flags=pyrender.RenderFlags.FLAT)
            inst = decode_ids(color[..., :3])
            inst[inst >= len(self.labels.lut)] = 0
            out["instance"] = inst
            out["semantic"] = self.labels.lut[inst]
        return out

    def close(self) -> None:
        if self.renderer is not None:
            release_offscreen(self.renderer)
            self.renderer = None
        if self.ids_renderer is not None:
            release_offscreen(self.ids_renderer)
            self.ids_renderer = None
