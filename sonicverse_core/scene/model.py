"""The scene model: static structure, dynamic objects, rooms, semantics and materials.

Static structure (walls, floors, ceilings, windows) never moves; it is what reverb probes are baked over. Dynamic
objects (furniture, doors, movable things) carry a pose; doors have an open state. Every piece of geometry has a
semantic category and an acoustic material. Coordinates: metres, z up.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
import trimesh

from sonicverse_core.errors import MeshError, PoseError
from sonicverse_core.scene.materials import MATERIAL_INDEX, get_material


class StructureKind(str, Enum):
    WALL = "wall"
    FLOOR = "floor"
    CEILING = "ceiling"
    WINDOW = "window"
    OTHER = "other"


def check_mesh(mesh: trimesh.Trimesh, what: str) -> trimesh.Trimesh:
    """Raise :class:`MeshError` for a mesh with no faces or non-finite vertices."""
    if mesh is None or len(mesh.faces) == 0:
        raise MeshError(f"{what}: mesh has no faces")
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshError(f"{what}: mesh has NaN or infinite vertex coordinates")
    return mesh


@dataclass
class StaticPart:
    """A piece of static structure in world coordinates."""

    name: str
    kind: StructureKind
    category: str
    material: str
    mesh: trimesh.Trimesh
    room: str | None = None

    def __post_init__(self):
        get_material(self.material)
        check_mesh(self.mesh, self.name)


def yaw_pose(x: float, y: float, z: float, yaw_deg: float) -> np.ndarray:
    """4x4 world-from-local transform: rotation ``yaw_deg`` about +z, then translation."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = (x, y, z)
    return m


@dataclass
class SceneObject:
    """A dynamic object: mesh in its local frame (z up, base at z=0), a world pose, semantics and material.

    ``mesh`` is the object's simple proxy (collision, navigation, footprints); ``parts`` (optional,
    :class:`sonicverse_core.scene.furniture.ObjectPart`: name, material or None for the object's own, mesh in the
    same local frame, colour) are what the cameras see and the acoustic engine hears; without parts the proxy is
    both."""

    name: str
    category: str
    material: str
    mesh: trimesh.Trimesh
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    movable: bool = False
    room: str | None = None
    parts: tuple = ()

    def __post_init__(self):
        get_material(self.material)
        check_mesh(self.mesh, self.name)
        for p in self.parts:
            if p.material is not None:
                get_material(p.material)
            check_mesh(p.mesh, f"{self.name}/{p.name}")
        self.pose = np.asarray(self.pose, dtype=float)

    def looks(self) -> list[tuple]:
        """(part name, material, local mesh, RGBA or None) of what is seen and heard: the parts, or the proxy."""
        if not self.parts:
            return [(self.category, self.material, self.mesh, None)]
        return [(p.name, p.material or self.material, p.mesh, p.colour) for p in self.parts]

    def set_pose(self, pose: np.ndarray) -> None:
        pose = np.asarray(pose, dtype=float)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise PoseError(f"{self.name}: pose must be a finite 4x4 matrix")
        self.pose = pose

    @property
    def position(self) -> np.ndarray:
        return self.pose[:3, 3].copy()

    def world_mesh(self) -> trimesh.Trimesh:
        m = self.mesh.copy()
        m.apply_transform(self.pose)
        return m

    def sound_position(self) -> np.ndarray:
        """(3,) where this object's sound comes from: the centre of its world bounds (a TV's screen, a sink's
        basin, a cushion's middle), wherever it is carried. The one place that says so: the renderer, the envs and
        the VR app all use it."""
        return self.world_bounds().mean(axis=0)

    def world_bounds(self, pose: np.ndarray | None = None) -> np.ndarray:
        """(2, 3) axis-aligned bounds in world coordinates (at ``pose``, default the current one)."""
        pose = self.pose if pose is None else pose
        kept = self.__dict__.get("_corners")  # the proxy's corners, made once per mesh (trimesh's bounds re-hash it)
        if kept is None or kept[0] is not self.mesh:
            kept = self._corners = (self.mesh, trimesh.bounds.corners(self.mesh.bounds))
        w = kept[1] @ pose[:3, :3].T + pose[:3, 3]
        return np.array([w.min(0), w.max(0)])


@dataclass
class Door(SceneObject):
    """A hinged door leaf. Its local frame has the hinge on the z axis and the leaf along +x when closed.

    ``closed_yaw`` is the leaf's yaw when closed, ``swing`` (+1 or -1) the direction it turns when opening, and
    ``open_fraction`` in [0, 1] maps to 0..90 degrees.
    """

    hinge: tuple = (0.0, 0.0)
    closed_yaw: float = 0.0
    swing: int = 1
    open_fraction: float = 1.0
    rooms: tuple = ()
    width: float = 0.86

    def __post_init__(self):
        super().__post_init__()
        self.set_open(self.open_fraction)

    def set_open(self, fraction: float) -> None:
        if not math.isfinite(fraction):
            raise PoseError(f"{self.name}: open fraction must be finite")
        self.open_fraction = float(min(max(fraction, 0.0), 1.0))
        yaw = self.closed_yaw + self.swing * 90.0 * self.open_fraction
        self.pose = yaw_pose(self.hinge[0], self.hinge[1], 0.0, yaw)

    @property
    def is_open(self) -> bool:
        return self.open_fraction > 0.5


def points_in_polygon(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd rule: bool (n,) for points (n, 2) inside polygon (k, 2)."""
    x, y = pts[:, 0:1], pts[:, 1:2]
    x0, y0 = poly[:, 0], poly[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    cond = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xint = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return np.count_nonzero(cond & (x < xint), axis=1) % 2 == 1


@dataclass
class Room:
    """A room: a type ('living room', 'kitchen', 'bedroom', 'bathroom', 'corridor'...), a name and a footprint."""

    name: str
    type: str
    footprint: np.ndarray  # (k, 2) polygon, counter-clockwise
    z_floor: float = 0.0
    z_ceiling: float = 2.6

    @property
    def area(self) -> float:
        x, y = self.footprint[:, 0], self.footprint[:, 1]
        return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))

    @property
    def volume(self) -> float:
        return self.area * (self.z_ceiling - self.z_floor)

    def contains(self, xy: np.ndarray) -> np.ndarray:
        """Bool mask of points (n, 2) inside the footprint."""
        return points_in_polygon(np.atleast_2d(xy), self.footprint)


@dataclass(frozen=True)
class SceneMesh:
    """Triangles of a set of parts, ready for ray casting.

    vertices : (v, 3) float64; faces : (f, 3) int64; face_material : (f,) int32 material ids;
    face_part : (f,) int32 index into ``part_names``; part_names : names of the parts.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_material: np.ndarray
    face_part: np.ndarray
    part_names: tuple

    @staticmethod
    def from_parts(parts: list[tuple[str, str, trimesh.Trimesh]]) -> "SceneMesh":
        verts, faces, mats, pids, names = [], [], [], [], []
        offset = 0
        for i, (name, material, mesh) in enumerate(parts):
            verts.append(np.asarray(mesh.vertices, dtype=float))
            faces.append(np.asarray(mesh.faces, dtype=np.int64) + offset)
            mats.append(np.full(len(mesh.faces), MATERIAL_INDEX[material], dtype=np.int32))
            pids.append(np.full(len(mesh.faces), i, dtype=np.int32))
            names.append(name)
            offset += len(mesh.vertices)
        if not parts:
            return SceneMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int32),
                             np.zeros(0, np.int32), ())
        return SceneMesh(np.concatenate(verts), np.concatenate(faces), np.concatenate(mats),
                         np.concatenate(pids), tuple(names))

    def __len__(self) -> int:
        return len(self.faces)


class Scene:
    """A household scene: static structure, dynamic objects, rooms; derived meshes are cached.

    ``dynamic_version`` increases whenever a dynamic object moves or a door opens or closes, so ray casters and
    renderers know when to rebuild their dynamic part.
    """

    def __init__(self, name: str, static: list[StaticPart], objects: list[SceneObject] | None = None,
                 rooms: list[Room] | None = None, spec: str | None = None, mapping_name: str = "builtin",
                 metadata: dict | None = None):
        if not static:
            raise MeshError(f"scene '{name}' has no static structure (no walls, floors or ceilings)")
        self.name = name
        self.spec = spec or name
        self.static = list(static)
        self.objects = list(objects or [])
        self.rooms = list(rooms or [])
        self.mapping_name = mapping_name
        self.metadata = dict(metadata or {})
        self.dynamic_version = 0
        self._static_mesh: SceneMesh | None = None
        self._dynamic_cache: dict = {}  # "looks" | "proxy" -> (dynamic_version, SceneMesh)
        self._world_cache: dict = {}  # (kind, name): (pose bytes, world vertices); (kind, name, "local"): arrays
        names = [o.name for o in self.objects]
        if len(set(names)) != len(names):
            raise MeshError(f"scene '{name}': object names must be unique")

    # --- objects -------------------------------------------------------------------------------------------
    def object(self, name: str) -> SceneObject:
        for o in self.objects:
            if o.name == name:
                return o
        from sonicverse_core.errors import SceneSpecError

        raise SceneSpecError(f"scene '{self.name}' has no object named '{name}'")

    @property
    def doors(self) -> list[Door]:
        return [o for o in self.objects if isinstance(o, Door)]

    def set_door(self, name: str, open_fraction: float) -> None:
        door = self.object(name)
        if not isinstance(door, Door):
            raise PoseError(f"'{name}' is not a door")
        door.set_open(open_fraction)
        self.touch()

    def move_object(self, name: str, pose: np.ndarray) -> None:
        self.object(name).set_pose(pose)
        self.touch()

    def touch(self) -> None:
        """Mark dynamic geometry as changed."""
        self.dynamic_version += 1

    # --- derived geometry -----------------------------------------------------------------------------------
    def static_mesh(self) -> SceneMesh:
        if self._static_mesh is None:
            self._static_mesh = SceneMesh.from_parts([(p.name, p.material, p.mesh) for p in self.static])
        return self._static_mesh

    def dynamic_mesh(self, proxies: bool = False) -> SceneMesh:
        """The objects in their current poses: what is seen and heard (their parts), or with ``proxies`` their
        simple proxies (collision and navigation). One part per object, named by the object: a door swinging costs
        the transform of its own vertices and one concatenation of per-object arrays."""
        key = "proxy" if proxies else "looks"
        hit = self._dynamic_cache.get(key)
        if hit is None or hit[0] != self.dynamic_version:
            verts, faces, mats, off = [], [], [], 0
            for o in self.objects:
                local = self._world_cache.get((key, o.name, "local"))
                if local is None:  # the object's parts as one array each, made once
                    looks = [(o.material, o.mesh)] if proxies else [(mat, m) for _, mat, m, _ in o.looks()]
                    v = np.concatenate([np.asarray(m.vertices, float) for _, m in looks])
                    n = np.cumsum([0] + [len(m.vertices) for _, m in looks[:-1]])
                    f = np.concatenate([np.asarray(m.faces, np.int64) + k for (_, m), k in zip(looks, n)])
                    mt = np.concatenate([np.full(len(m.faces), MATERIAL_INDEX[mat], np.int32) for mat, m in looks])
                    local = self._world_cache[(key, o.name, "local")] = (v, f, mt)
                pose = o.pose.tobytes()
                w = self._world_cache.get((key, o.name))
                if w is None or w[0] != pose:  # only objects that moved are transformed again
                    w = self._world_cache[(key, o.name)] = (pose, local[0] @ o.pose[:3, :3].T + o.pose[:3, 3])
                verts.append(w[1])
                faces.append(local[1] + off)
                mats.append(local[2])
                off += len(w[1])
            if verts:
                mesh = SceneMesh(np.concatenate(verts), np.concatenate(faces), np.concatenate(mats),
                                 np.repeat(np.arange(len(self.objects), dtype=np.int32), [len(f) for f in faces]),
                                 tuple(o.name for o in self.objects))
            else:
                mesh = SceneMesh.from_parts([])
            hit = self._dynamic_cache[key] = (self.dynamic_version, mesh)
        return hit[1]

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) bounds of the static structure."""
        v = self.static_mesh().vertices
        return np.array([v.min(0), v.max(0)])

    @property
    def floor_z(self) -> float:
        floors = [p for p in self.static if p.kind == StructureKind.FLOOR]
        if floors:
            return float(min(p.mesh.bounds[1, 2] for p in floors))
        return float(self.bounds[0, 2])

    def static_hash(self) -> str:
        """Content hash of the static structure and its materials (keys reverb bakes)."""
        h = hashlib.sha256()
        sm = self.static_mesh()
        h.update(np.ascontiguousarray(np.round(sm.vertices, 5)).tobytes())
        h.update(np.ascontiguousarray(sm.faces).tobytes())
        for p in self.static:
            h.update(p.material.encode())
            h.update(b"\0")
        return h.hexdigest()

    @property
    def triangle_count(self) -> int:
        return len(self.static_mesh()) + sum(sum(len(m.faces) for _, _, m, _ in o.looks()) for o in self.objects)

    def room_at(self, xy) -> Room | None:
        for r in self.rooms:
            if r.contains(np.asarray(xy, dtype=float)[:2])[0]:
                return r
        return None
