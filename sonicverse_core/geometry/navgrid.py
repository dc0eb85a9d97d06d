"""Navigability grid for a ground robot, geodesic distances and shortest paths.

A cell is floor when a ray cast straight down from ``robot_height`` above the floor level first meets an
upward-facing surface within ``max_step`` of the floor (every supersample of the cell must). Anything else (a wall,
furniture lower than the robot, the inside of a solid, nothing at all) is blocked. The free space is eroded by the
robot radius (plus half a cell, so the discretisation never lets the robot clip an obstacle).

Geodesic distance fields use Dijkstra on a 16-neighbour grid graph (moves (1,0), (1,1), (1,2) and their
symmetries; at most 2.7% longer than the true any-angle distance in open space). Point-to-point shortest paths are
then string-pulled with line-of-sight checks, so in an empty room they equal the straight line.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import ndimage
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from sonicverse_core.errors import ConfigError, PoseError
from sonicverse_core.scene.model import Scene

MAX_CELLS = 16_000_000  # cells of one grid (200 m x 200 m at 5 cm): its geodesic graph stays within ~1.5 GB
RAYS_PER_BATCH = 1 << 20  # the floor rays are cast in batches: memory bounded by the grid, not the ray count

_MOVES = [(dy, dx) for dy in range(-2, 3) for dx in range(-2, 3)
          if (dy, dx) != (0, 0) and max(abs(dy), abs(dx)) <= 2 and np.gcd(abs(dy), abs(dx)) == 1]


MAX_CELL = 0.5  # m: NavConfig's largest cell


def coarsest_cell(scene: Scene, cells: int) -> float:
    """The cell (m, rounded up to the centimetre, with 5% to spare for the grid's margin) at which the scene's floor
    plan fits in ``cells`` cells; may exceed ``MAX_CELL``."""
    lo, hi = scene.bounds[0, :2], scene.bounds[1, :2]
    return float(np.ceil(np.sqrt((hi[0] - lo[0]) * (hi[1] - lo[1]) / cells) * 100 * 1.05) / 100)


@dataclass(frozen=True)
class NavConfig:
    """cell (m, 0.05-0.1 sensible); robot_radius (m, TurtleBot 2: 0.18); robot_height (m): obstacles lower than
    this block the robot; max_step (m): the highest sill it drives over; supersample: rays per cell side."""

    cell: float = 0.05
    robot_radius: float = 0.18
    robot_height: float = 0.5
    max_step: float = 0.05
    supersample: int = 2

    def __post_init__(self):
        if not (0.01 <= self.cell <= MAX_CELL):
            raise ConfigError(f"navigation cell size must be within 0.01..{MAX_CELL} m, got {self.cell}")
        if self.robot_radius < 0 or self.robot_height <= 0:
            raise ConfigError("robot radius and height must be positive")


class NavGrid:
    """Navigable cells of a scene at one floor level, with doors and objects in their current state."""

    def __init__(self, scene: Scene, config: NavConfig = NavConfig(), caster=None, z_floor: float | None = None):
        from sonicverse_core.geometry.raycast import SceneRayCaster

        self.scene = scene
        self.config = config
        self.caster = caster or SceneRayCaster(scene, proxies=True)  # objects as their proxies
        self.z_floor = scene.floor_z if z_floor is None else float(z_floor)
        c = config.cell
        lo, hi = scene.bounds[0, :2], scene.bounds[1, :2]
        # one empty cell of margin on every side: the scene's edge is an obstacle for the distance transform
        self.origin = np.floor(lo / c) * c - c
        self.shape = (int(np.ceil((hi[1] - self.origin[1]) / c)) + 2, int(np.ceil((hi[0] - self.origin[0]) / c)) + 2)
        ny, nx = self.shape
        if ny * nx > MAX_CELLS:
            suggest = coarsest_cell(scene, MAX_CELLS)
            fix = (f"use NavConfig(cell={suggest:.2f}) or a smaller scene" if suggest <= MAX_CELL
                   else f"no cell up to {MAX_CELL} m fits it: use a smaller scene")
            raise ConfigError(f"the scene's floor plan ({hi[0] - lo[0]:.0f} x {hi[1] - lo[1]:.0f} m) needs "
                              f"{ny * nx / 1e6:.0f}M navigation cells of {c} m (at most {MAX_CELLS / 1e6:.0f}M): "
                              + fix)
        ss = config.supersample
        sub = (np.arange(ss) + 0.5) / ss
        xs = self.origin[0] + (np.arange(nx)[:, None] + sub[None]).ravel() * c
        z0 = self.z_floor + config.robot_height
        floor = np.zeros((ny * ss, nx * ss), dtype=bool)
        rows_per = max(1, RAYS_PER_BATCH // len(xs))
        for r0 in range(0, ny * ss, rows_per):  # a batch of supersample rows at a time
            r = np.arange(r0, min(r0 + rows_per, ny * ss))
            ys = self.origin[1] + (r // ss + sub[r % ss]) * c
            gx, gy = np.meshgrid(xs, ys)
            o = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z0)], axis=1)
            d = np.zeros_like(o)
            d[:, 2] = -1.0
            h = self.caster.first_hit(o, d, config.robot_height + 1.0)
            hit_z = z0 - h.distance
            ok = h.hit & (h.normal[:, 2] > 0.7) & (np.abs(hit_z - self.z_floor) <= config.max_step)
            if "traversable" in scene.metadata:  # iGibson ships its own traversability map: respect it too
                from sonicverse_core.scene.loaders.igibson import traversable_at

                ok &= traversable_at(scene, o[:, :2])
            floor[r] = ok.reshape(len(r), -1)
        floor = floor.reshape(ny, ss, nx, ss).all(axis=(1, 3))
        floor &= ~self._vertical_obstacles(scene)
        self._finish(floor)

    def derive(self, blocked: np.ndarray) -> "NavGrid":
        """A grid over the same floor with the cells in ``blocked`` (bool, grid shape) taken away: how the world
        adds doors and movable objects to a grid of the fixed structure without casting rays again."""
        g = object.__new__(NavGrid)
        g.scene, g.config, g.caster, g.z_floor = self.scene, self.config, self.caster, self.z_floor
        g.origin, g.shape = self.origin, self.shape
        g._finish(self.floor & ~blocked)
        return g

    def _finish(self, floor: np.ndarray) -> None:
        c = self.config.cell
        self.floor = floor
        edt = ndimage.distance_transform_edt(floor) * c
        self.clearance = edt
        self.navigable = edt >= self.config.robot_radius + 0.5 * c
        self.labels, self.n_components = ndimage.label(self.navigable, structure=np.ones((3, 3)))
        if self.n_components:
            sizes = np.bincount(self.labels.ravel())[1:]
            self.main_label = int(np.argmax(sizes)) + 1
        else:
            self.main_label = -1  # no component: no cell matches (labels are >= 0)
        for arr in (self.floor, self.navigable, self.labels, self.clearance):
            arr.setflags(write=False)

    def _vertical_obstacles(self, scene: Scene) -> np.ndarray:
        """Cells crossed by near-vertical faces within the robot's height band (thin walls that downward rays
        cannot see), found by sampling each face on a lattice finer than half a cell."""
        c, cfg = self.config.cell, self.config
        out = np.zeros(self.shape, dtype=bool)
        zlo, zhi = self.z_floor + cfg.max_step, self.z_floor + cfg.robot_height
        for mesh in (scene.static_mesh(), scene.dynamic_mesh(proxies=True)):
            if len(mesh) == 0:
                continue
            tri = mesh.vertices[mesh.faces]
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            ln = np.linalg.norm(n, axis=1)
            vert = (ln > 0) & (np.abs(n[:, 2]) < 0.5 * np.maximum(ln, 1e-300))
            vert &= (tri[:, :, 2].min(1) < zhi) & (tri[:, :, 2].max(1) > zlo)
            tri = tri[vert]
            if len(tri) == 0:
                continue
            # horizontal cross-sections of each face at 5 heights in the band, sampled every 0.4 cell
            segs = []
            for z in np.linspace(zlo, zhi, 5):
                z0, z1 = tri[:, :, 2], np.roll(tri[:, :, 2], -1, axis=1)
                with np.errstate(divide="ignore", invalid="ignore"):
                    t = (z - z0) / (z1 - z0)
                ok = (t >= 0) & (t <= 1) & np.isfinite(t)
                t = np.where(ok, t, 0.0)
                pe = tri + t[..., None] * (np.roll(tri, -1, axis=1) - tri)
                two = ok.sum(1) >= 2
                first = np.argmax(ok, axis=1)
                last = 2 - np.argmax(ok[:, ::-1], axis=1)
                idx = np.flatnonzero(two)
                segs.append(np.stack([pe[idx, first[idx], :2], pe[idx, last[idx], :2]], 1))
            inside = tri[(tri[:, :, 2] >= zlo) & (tri[:, :, 2] <= zhi)][:, :2]
            segs.append(np.stack([inside, inside], 1))
            sg = np.concatenate(segs)
            n_s = np.ceil(np.linalg.norm(sg[:, 1] - sg[:, 0], axis=1) / (0.4 * c)).astype(int) + 1
            rep = np.repeat(np.arange(len(sg)), n_s)
            f = (np.arange(n_s.sum()) - np.repeat(np.cumsum(n_s) - n_s, n_s)) / np.maximum(np.repeat(n_s, n_s) - 1, 1)
            p = sg[rep, 0] + f[:, None] * (sg[rep, 1] - sg[rep, 0])
            rc = self.cell_of(p)
            ok = self._in_grid(rc)
            out[rc[ok, 0], rc[ok, 1]] = True
        return out

    # --- coordinates --------------------------------------------------------------------------------------------
    def cell_of(self, xy) -> np.ndarray:
        """(n, 2) int (row, col) of points (n, 2); may be out of the grid."""
        xy = np.atleast_2d(np.asarray(xy, dtype=float))[:, :2]
        if not np.all(np.isfinite(xy)):
            raise PoseError("positions must be finite")
        return np.floor((xy[:, ::-1] - self.origin[::-1]) / self.config.cell).astype(np.int64)

    def center_of(self, rc) -> np.ndarray:
        rc = np.atleast_2d(rc)
        return self.origin + (rc[:, ::-1] + 0.5) * self.config.cell

    def _in_grid(self, rc):
        return (rc[:, 0] >= 0) & (rc[:, 0] < self.shape[0]) & (rc[:, 1] >= 0) & (rc[:, 1] < self.shape[1])

    def is_navigable(self, xy, main_only: bool = True) -> np.ndarray:
        rc = self.cell_of(xy)
        ok = self._in_grid(rc)
        out = np.zeros(len(rc), dtype=bool)
        r, cc = rc[ok, 0], rc[ok, 1]
        out[ok] = (self.labels[r, cc] == self.main_label) if main_only else self.navigable[r, cc]
        return out

    @property
    def navigable_area(self) -> float:
        return float(np.count_nonzero(self.labels == self.main_label)) * self.config.cell ** 2

    def unreachable_rooms(self, min_area: float = 0.25) -> list[str]:
        """Rooms with less than ``min_area`` m^2 of the main navigable component."""
        rows, cols = np.nonzero(self.labels == self.main_label)
        centers = self.center_of(np.stack([rows, cols], 1)) if len(rows) else np.zeros((0, 2))
        bad = []
        for room in self.scene.rooms:
            n = np.count_nonzero(room.contains(centers)) if len(centers) else 0
            if n * self.config.cell ** 2 < min_area:
                bad.append(room.name)
        return bad

    # --- sampling ------------------------------------------------------------------------------------------------
    def sample(self, rng: np.random.Generator, n: int = 1, room: str | None = None) -> np.ndarray:
        """(n, 2) points uniformly over the main navigable component (optionally inside one room)."""
        mask = self.labels == self.main_label
        rows, cols = np.nonzero(mask)
        if room is not None:
            r = next((x for x in self.scene.rooms if x.name == room), None)
            if r is None:
                raise ConfigError(f"no room named '{room}'")
            keep = r.contains(self.center_of(np.stack([rows, cols], 1)))
            rows, cols = rows[keep], cols[keep]
        if len(rows) == 0:
            raise ConfigError("no navigable floor to sample from")
        idx = rng.integers(0, len(rows), n)
        return self.center_of(np.stack([rows[idx], cols[idx]], 1))

    # --- geodesics ----------------------------------------------------------------------------------------------
    @cached_property
    def _graph(self):
        ny, nx = self.shape
        ids = -np.ones(self.shape, dtype=np.int32)
        nav = self.labels > 0
        ids[nav] = np.arange(np.count_nonzero(nav), dtype=np.int32)
        src, dst, w = [], [], []
        pad = np.pad(nav, 2)
        for dy, dx in _MOVES:
            ok = nav & pad[2 + dy:2 + dy + ny, 2 + dx:2 + dx + nx]
            if abs(dy) == 2 or abs(dx) == 2:  # knight move: both cells it passes must be free
                hy, hx = int(np.sign(dy)), int(np.sign(dx))
                ok &= pad[2 + hy:2 + hy + ny, 2 + hx:2 + hx + nx]
                ok &= pad[2 + (dy - hy):2 + (dy - hy) + ny, 2 + (dx - hx):2 + (dx - hx) + nx]
            r, c = np.nonzero(ok)
            src.append(ids[r, c])
            dst.append(ids[r + dy, c + dx])
            w.append(np.full(len(r), np.hypot(dy, dx) * self.config.cell))
        n = int(np.count_nonzero(nav))
        g = csr_matrix((np.concatenate(w), (np.concatenate(src), np.concatenate(dst))), shape=(n, n))
        return g, ids

    def _snap(self, xy) -> tuple[int, np.ndarray]:
        """Graph node of the navigable cell nearest to point xy (main component), and that cell's centre."""
        g, ids = self._graph
        rc = self.cell_of(xy)[0]
        if self._in_grid(rc[None])[0] and self.labels[rc[0], rc[1]] == self.main_label:
            return int(ids[rc[0], rc[1]]), self.center_of(rc)[0]
        rows, cols = np.nonzero(self.labels == self.main_label)
        if len(rows) == 0:
            raise ConfigError("the scene has no navigable floor")
        k = int(np.argmin((rows - rc[0]) ** 2 + (cols - rc[1]) ** 2))
        return int(ids[rows[k], cols[k]]), self.center_of((rows[k], cols[k]))[0]

    def distance_field(self, goal_xy) -> np.ndarray:
        """(ny, nx) geodesic distance (m) from every cell to the goal, or to the nearest of several goals (k, 2)
        (one multi-source Dijkstra; goals are taken at their cells' centres); inf where unreachable."""
        g, ids = self._graph
        goals = np.atleast_2d(np.asarray(goal_xy, float))[:, :2]
        snapped = [self._snap(p) for p in goals]
        nodes = [n for n, _ in snapped]
        if len(goals) == 1:
            d = dijkstra(g, indices=nodes[0])
            d = d + float(np.linalg.norm(snapped[0][1] - goals[0]))
        else:
            d = dijkstra(g, indices=nodes, min_only=True)
        out = np.full(self.shape, np.inf)
        nav = ids >= 0
        out[nav] = d[ids[nav]]
        return out

    def geodesic_from_field(self, field: np.ndarray, xy) -> np.ndarray:
        rc = self.cell_of(xy)
        ok = self._in_grid(rc)
        out = np.full(len(rc), np.inf)
        out[ok] = field[rc[ok, 0], rc[ok, 1]]
        return out

    def line_of_sight(self, a, b) -> bool:
        a, b = np.asarray(a, float)[:2], np.asarray(b, float)[:2]
        n = int(np.ceil(np.linalg.norm(b - a) / (0.25 * self.config.cell))) + 1
        pts = a + np.linspace(0, 1, n)[:, None] * (b - a)
        return bool(np.all(self.is_navigable(pts)))

    def shortest_path(self, a, b) -> tuple[np.ndarray, float]:
        """Waypoints (k, 2) from a to b along navigable floor, string-pulled, and their length (inf: none)."""
        a, b = np.asarray(a, float)[:2], np.asarray(b, float)[:2]
        g, ids = self._graph
        na, ca = self._snap(a)
        nb, cb = self._snap(b)
        dist, pred = dijkstra(g, indices=na, return_predecessors=True)
        if not np.isfinite(dist[nb]):
            return np.zeros((0, 2)), float("inf")
        rows, cols = np.nonzero(ids >= 0)
        order = np.argsort(ids[rows, cols])
        centers = self.center_of(np.stack([rows[order], cols[order]], 1))
        chain = [nb]
        while chain[-1] != na:
            chain.append(int(pred[chain[-1]]))
        pts = [a] + [centers[i] for i in reversed(chain)] + [b]
        # string pulling: from each kept point walk forward while the next point is still in sight
        out = [pts[0]]
        i = 0
        while i < len(pts) - 1:
            j = i + 1
            while j + 1 < len(pts) and self.line_of_sight(pts[i], pts[j + 1]):
                j += 1
            out.append(pts[j])
            i = j
        path = np.array(out)
        return path, float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))

    def geodesic_distance(self, a, b) -> float:
        return self.shortest_path(a, b)[1]
