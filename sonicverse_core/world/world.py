"""The world a robot drives in: a scene, its collision map, one differential-drive robot, doors that open and
close, and objects that can be picked up, carried and put down (their sounds move with them).

Collision map: a :class:`NavGrid` of the scene's fixed structure (walls, floors, furniture that never moves) is
built once by ray casting; doors and movable objects are rasterised onto it (their footprint in the robot's height
band) and the clearance is recomputed only when one of them changes. The robot's centre may be wherever the
clearance is at least its radius (plus half a cell).
"""
from __future__ import annotations

import math

import numpy as np

from sonicverse_core.errors import ActionError, ConfigError, PoseError
from sonicverse_core.geometry.navgrid import NavConfig, NavGrid
from sonicverse_core.scene.model import Door, Scene, points_in_polygon, yaw_pose
from sonicverse_core.world.robot import RobotConfig, integrate, wheel_action

REACH = 0.5  # m from the robot's edge to an object's footprint for picking it up


def _moves(o) -> bool:
    return isinstance(o, Door) or o.movable


def footprint_polygon(o, z_lo: float, z_hi: float) -> np.ndarray | None:
    """Convex (k, 2) footprint of object ``o`` where it meets the height band [z_lo, z_hi]; None if it does not."""
    v = o.mesh.vertices @ o.pose[:3, :3].T + o.pose[:3, 3]
    if v[:, 2].max() < z_lo or v[:, 2].min() > z_hi:
        return None
    from scipy.spatial import ConvexHull, QhullError

    xy = v[:, :2]
    try:
        return xy[ConvexHull(xy).vertices]
    except (QhullError, ValueError):
        lo, hi = xy.min(0), xy.max(0)
        return np.array([lo, [hi[0], lo[1]], hi, [lo[0], hi[1]]])


def box_distance(lo: np.ndarray, hi: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Horizontal distance from points (n, 2) to the axis-aligned box [lo, hi] (0 inside)."""
    return np.linalg.norm(np.maximum(np.maximum(lo - pts, pts - hi), 0.0), axis=-1)


def _segment_distance(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Distance from points (n, 2) to the boundary of polygon (k, 2)."""
    a, b = poly, np.roll(poly, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("nkd,kd->nk", p[:, None] - a[None], ab) / np.maximum((ab * ab).sum(1), 1e-12), 0, 1)
    q = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(p[:, None] - q, axis=2).min(1)


class World:
    """A scene with a robot. ``drive(action, dt)`` moves it; ``set_door``, ``pick``, ``place`` change the world."""

    def __init__(self, scene: Scene, robot: RobotConfig = RobotConfig(), nav: NavConfig | None = None):
        self.scene = scene
        self.robot = robot
        self.nav = nav or NavConfig(robot_radius=max(robot.radius, 0.05), robot_height=0.5)
        fixed = [o for o in scene.objects if not _moves(o)]
        base = Scene(scene.name, scene.static, fixed, scene.rooms, spec=scene.spec, mapping_name=scene.mapping_name,
                     metadata=scene.metadata)
        self.base = NavGrid(base, self.nav)
        self._initial = {o.name: (o.pose.copy(), getattr(o, "open_fraction", None)) for o in scene.objects}
        self.carried: str | None = None
        self._fp: dict[str, tuple[bytes, np.ndarray]] = {}
        self.grid = self.base
        self._rebuild()
        self.pose = np.array([*self.grid.sample(np.random.default_rng(0))[0], 0.0])
        self.bumped = False
        #: moving bodies that are not part of the scene (a person): name -> (xy (2,), radius m). The robot cannot
        #: move into one, but may always move away from a body that came onto it.
        self.bodies: dict[str, tuple[np.ndarray, float]] = {}

    # --- collision map ----------------------------------------------------------------------------------------
    def _cells(self, o) -> np.ndarray:
        """Flat indices of the cells object ``o`` blocks at its current pose (cached per pose)."""
        key = o.pose.tobytes()
        hit = self._fp.get(o.name)
        if hit is not None and hit[0] == key:
            return hit[1]
        z0 = self.base.z_floor
        poly = footprint_polygon(o, z0 + self.nav.max_step, z0 + self.nav.robot_height)
        idx = np.zeros(0, np.int64)
        if poly is not None:
            c = self.nav.cell
            rc0 = self.base.cell_of(poly.min(0) - c)[0]
            rc1 = self.base.cell_of(poly.max(0) + c)[0]
            r = np.arange(max(rc0[0], 0), min(rc1[0], self.base.shape[0] - 1) + 1)
            cc = np.arange(max(rc0[1], 0), min(rc1[1], self.base.shape[1] - 1) + 1)
            if len(r) and len(cc):
                R, C = np.meshgrid(r, cc, indexing="ij")
                R, C = R.ravel(), C.ravel()
                ctr = self.base.center_of(np.stack([R, C], 1))
                near = points_in_polygon(ctr, poly) | (_segment_distance(ctr, poly) <= 0.75 * c)
                idx = np.ravel_multi_index((R[near], C[near]), self.base.shape)
        self._fp[o.name] = (key, idx)
        return idx

    def _rebuild(self) -> None:
        blocked = np.zeros(self.base.shape, bool)
        for o in self.scene.objects:
            if _moves(o) and o.name != self.carried:
                blocked.flat[self._cells(o)] = True
        self.grid = self.base.derive(blocked)
        self._nav_flat = self.grid.navigable.ravel()

    def free(self, x: float, y: float) -> bool:
        """Whether the robot's centre may be at (x, y)."""
        g = self.grid
        c = g.config.cell
        col = math.floor((x - g.origin[0]) / c)
        row = math.floor((y - g.origin[1]) / c)
        if not (0 <= row < g.shape[0] and 0 <= col < g.shape[1]):
            return False
        if not self._nav_flat[row * g.shape[1] + col]:
            return False
        for xy, r in self.bodies.values():
            lim = r + self.robot.radius
            d2 = (x - xy[0]) ** 2 + (y - xy[1]) ** 2
            if d2 < lim * lim and d2 < (self.pose[0] - xy[0]) ** 2 + (self.pose[1] - xy[1]) ** 2:
                return False
        return True

    # --- robot ------------------------------------------------------------------------------------------------
    def place_robot(self, x: float, y: float, yaw: float) -> None:
        if not all(math.isfinite(v) for v in (x, y, yaw)):
            raise PoseError(f"robot pose must be finite, got ({x}, {y}, {yaw})")
        if not self.free(x, y):
            raise PoseError(f"the robot does not fit at ({x:.2f}, {y:.2f}): a wall or an object is in the way")
        self.pose = np.array([x, y, (yaw + 180.0) % 360.0 - 180.0])
        self.bumped = False
        self._carry_along()

    def drive(self, action, dt: float) -> float:
        """Apply normalised wheel velocities for ``dt`` seconds; returns the distance travelled (m)."""
        wheels = wheel_action(action)
        if not (math.isfinite(dt) and dt > 0):
            raise ConfigError(f"time step must be a positive number, got {dt}")
        self.pose, self.bumped, travelled = integrate(self.robot, self.pose, wheels, dt, self.free)
        self._carry_along()
        return travelled

    @property
    def ears(self) -> np.ndarray:
        return np.array([self.pose[0], self.pose[1], self.base.z_floor + self.robot.ear_height])

    @property
    def camera(self) -> tuple:
        return (self.pose[0], self.pose[1], self.base.z_floor + self.robot.camera_height, self.pose[2])

    # --- doors ------------------------------------------------------------------------------------------------
    def set_door(self, name: str, open_fraction: float) -> None:
        """Open (1) or close (0) a door. A door that would swing into the robot is refused (ActionError)."""
        door = self.scene.object(name)
        if not isinstance(door, Door):
            raise ActionError(f"'{name}' is not a door")
        if not math.isfinite(open_fraction):
            raise PoseError(f"{name}: open fraction must be finite")
        before = door.open_fraction
        z0 = self.base.z_floor
        p = self.pose[:2][None]
        for f in np.linspace(before, min(max(open_fraction, 0.0), 1.0), 12)[1:]:
            door.set_open(f)  # the leaf's sweep, checked against the robot's body
            poly = footprint_polygon(door, z0 + self.nav.max_step, z0 + self.nav.robot_height)
            hits = poly is not None and (points_in_polygon(p, poly)[0]
                                         or _segment_distance(p, poly)[0] < self.robot.radius)
            if hits:
                door.set_open(before)
                raise ActionError(f"{name} cannot move: the robot is in its way")
        self.scene.set_door(name, open_fraction)
        self._rebuild()

    # --- carrying ---------------------------------------------------------------------------------------------
    def reach_distance(self, name: str) -> float:
        """Horizontal distance (m) from the robot's edge to the object's footprint."""
        o = self.scene.object(name)
        lo, hi = o.world_bounds()[:, :2]
        return float(max(box_distance(lo, hi, self.pose[:2]) - self.robot.radius, 0.0))

    def pick(self, name: str) -> None:
        o = self.scene.object(name)
        if self.carried is not None:
            raise ActionError(f"already carrying {self.carried}; put it down first")
        if not o.movable:
            raise ActionError(f"{name} ({o.category}) cannot be picked up")
        d = self.reach_distance(name)
        if d > REACH:
            raise ActionError(f"{name} is {d:.2f} m away; come within {REACH} m to pick it up")
        self.carried = name
        self._carry_along()
        self._rebuild()

    def place(self) -> str:
        """Put the carried object down on the floor in front of the robot; returns its name."""
        if self.carried is None:
            raise ActionError("not carrying anything")
        o = self.scene.object(self.carried)
        half = 0.5 * float(np.max(o.mesh.extents[:2]))
        a = math.radians(self.pose[2])
        d = self.robot.radius + half + 0.05
        x, y = self.pose[0] + d * math.cos(a), self.pose[1] + d * math.sin(a)
        old = o.pose.copy()
        o.set_pose(yaw_pose(x, y, self.base.z_floor + 0.005, self.pose[2]))
        cells = self._cells(o)
        rr, cc = np.unravel_index(cells, self.base.shape)
        if len(cells) and not np.all(self.base.floor[rr, cc]):
            o.set_pose(old)
            raise ActionError(f"no room to put {o.name} down in front of the robot")
        name, self.carried = self.carried, None
        self.scene.touch()
        self._rebuild()
        if not self.free(self.pose[0], self.pose[1]):
            self.carried = name
            o.set_pose(old)
            self.scene.touch()
            self._rebuild()
            raise ActionError(f"no room to put {o.name} down in front of the robot")
        return name

    def _carry_along(self) -> None:
        if self.carried is not None:
            x, y, yaw = self.pose
            self.scene.move_object(self.carried, yaw_pose(x, y, self.base.z_floor + self.robot.height, yaw))

    def restore(self) -> None:
        """Every object and door back where the scene started (a new episode)."""
        changed = self.carried is not None
        self.carried = None
        self.bodies = {}
        for o in self.scene.objects:
            pose, frac = self._initial[o.name]
            if isinstance(o, Door):
                if o.open_fraction != frac:
                    o.set_open(frac)
                    changed = True
            elif not np.array_equal(o.pose, pose):
                o.set_pose(pose.copy())
                changed = True
        if changed:
            self.scene.touch()
            self._rebuild()
