"""Rooms of a scene that does not name them (a mesh, a scan): regions of free floor joined by narrow openings.

The free floor of the navigation grid (furniture footprints filled in: they stand in a room) is eroded by its
distance transform: cells farther than ``opening`` from any wall are room cores, and a doorway narrower than
2 x ``opening`` separates two cores. Each core of at least ``min_core`` m^2 is a room; it grows back through the
free floor (a dilation constrained to the floor, so it never crosses a wall) until every free cell belongs to a
room. The room's footprint is the outline of its cells; its ceiling is found by casting rays up.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from sonicverse_core.scene.model import Room

OPENING = 0.5  # m: half the width of the widest opening that still separates two rooms (doors are 0.8-1.0 m)
MIN_CORE = 0.5  # m^2: smaller cores (a niche, a wide doorway's middle) are not rooms of their own


def segment_rooms(grid, opening: float = OPENING, min_core: float = MIN_CORE) -> list[Room]:
    """Rooms (type 'unknown', named 'room 1', 'room 2'... by decreasing area) from a
    :class:`~sonicverse_core.geometry.navgrid.NavGrid`; empty when the scene has no free floor."""
    c = grid.config.cell
    free = ndimage.binary_fill_holes(grid.floor)  # furniture footprints belong to their room...
    free &= ~_inside_solids(grid, free)  # ...the inside of a column does not
    if not free.any():
        return []
    dist = ndimage.distance_transform_edt(free) * c
    core = dist >= opening
    if not core.any():  # no part of the floor is that far from a wall: the whole floor is one small room
        core = dist >= 0.5 * dist.max()
    labels, n = ndimage.label(core, structure=np.ones((3, 3)))
    sizes = np.bincount(labels.ravel(), minlength=n + 1) * c * c
    keep = np.zeros(n + 1, bool)
    keep[1:] = sizes[1:] >= min_core
    if not keep.any():
        keep[int(np.argmax(sizes[1:])) + 1] = True
    labels = np.where(keep[labels], labels, 0)
    for _ in range(int(np.ceil(max(grid.shape) * 2))):  # grow through the free floor, never across a wall
        grown = ndimage.grey_dilation(labels, size=(3, 3))
        add = (labels == 0) & free & (grown > 0)
        if not add.any():
            break
        labels[add] = grown[add]
    ids = [int(i) for i in np.unique(labels) if i > 0]
    cells = {i: labels == i for i in ids}
    ids.sort(key=lambda i: -int(cells[i].sum()))
    rooms = []
    for k, i in enumerate(ids, 1):
        poly = _outline(cells[i], grid.origin, c)
        if poly is None:
            continue
        rooms.append(Room(f"room {k}", "unknown", poly, float(grid.z_floor), _ceiling(grid, cells[i])))
    return rooms


def _inside_solids(grid, free: np.ndarray) -> np.ndarray:
    """Cells of ``free`` inside a closed solid (a column, a wall's box): along oblique rays from 1 m above the floor
    the first surface is met from its back (the normal points along the ray) and belongs to a watertight part, for
    at least 3 of 4 directions. (Straight down or up cannot tell: inside a column that stands on the floor and
    reaches the ceiling its faces and the floor's or ceiling's coincide.)"""
    out = np.zeros(grid.shape, bool)
    rows, cols = np.nonzero(free)
    if not len(rows):
        return out
    xy = grid.center_of(np.stack([rows, cols], 1))
    o = np.c_[xy, np.full(len(xy), grid.z_floor + 1.0)]
    static = grid.scene.static
    closed = np.array([p.mesh.is_watertight for p in static] + [False])
    votes = np.zeros(len(o), int)
    for d in ((1.0, 0.31, 0.17), (-0.37, 1.0, 0.13), (-1.0, -0.53, 0.11), (0.29, -1.0, -0.19)):
        d = np.asarray(d) / np.linalg.norm(d)
        h = grid.caster.first_hit(o, np.tile(d, (len(o), 1)), 1000.0, include_dynamic=False)
        part = np.where(h.hit, h.part, len(static))
        votes += h.hit & (h.normal @ d > 0.05) & closed[np.clip(part, 0, len(static))]
    inside = votes >= 3
    out[rows[inside], cols[inside]] = True
    return out


def _outline(mask: np.ndarray, origin: np.ndarray, cell: float) -> np.ndarray | None:
    """Counter-clockwise polygon (k, 2) of the outer boundary of a region of cells (its holes filled)."""
    import contourpy

    m = np.pad(ndimage.binary_fill_holes(mask), 1).astype(float)
    lines = contourpy.contour_generator(z=m, line_type="Separate").lines(0.5)
    if not lines:
        return None
    line = max(lines, key=len)  # index coordinates (col, row) of the padded grid
    xy = origin + (np.asarray(line, float) - 1 + 0.5) * cell
    if np.allclose(xy[0], xy[-1]):
        xy = xy[:-1]
    x, y = xy[:, 0], xy[:, 1]
    if np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)) < 0:
        xy = xy[::-1]
    return xy if len(xy) >= 3 else None


def _ceiling(grid, mask: np.ndarray, samples: int = 64) -> float:
    """Median height of the first surface above the room's floor (rays cast up from its cells)."""
    rows, cols = np.nonzero(mask)
    pick = np.linspace(0, len(rows) - 1, min(samples, len(rows))).astype(int)
    xy = grid.center_of(np.stack([rows[pick], cols[pick]], 1))
    z0 = grid.z_floor + 0.05
    o = np.c_[xy, np.full(len(xy), z0)]
    d = np.tile([0.0, 0.0, 1.0], (len(o), 1))
    h = grid.caster.first_hit(o, d, 100.0, include_dynamic=False)  # furniture is no ceiling
    top = z0 + h.distance[h.hit]
    return float(np.median(top)) if len(top) else float(grid.scene.bounds[1, 2])
