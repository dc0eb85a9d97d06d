"""The embedded default scene: ``builtin:apartment?seed=N``, a procedural home.

Layout: a rectangular flat of 3-8 rooms. Homes of 5+ rooms are double-loaded around a corridor (every room has a door
to it, and a kitchen next to the living room gets a door of its own); smaller homes open every room onto the living
room. Walls are 0.12 m thick, ceilings 2.5-2.8 m; hinged doors swing into rooms; windows sit in the outer walls.
Furniture of the 15 sounding categories is placed the way people furnish rooms (a bed with its head on a wall,
a toilet, sink and shower in the bathroom, countertop and sink against the kitchen wall, a table with chairs...),
never inside a wall, in front of a door swing or a window (for tall pieces). A navigability check on the finished
scene removes optional pieces until every room is reachable by the robot.

Seeds are split so that test homes are never seen in training: :data:`SPLITS`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import trimesh

from sonicverse_core.errors import SceneSpecError
from sonicverse_core.scene import furniture
from sonicverse_core.scene.mapping import MAPPINGS, CategoryMapping
from sonicverse_core.scene.model import Door, Room, Scene, SceneObject, StaticPart, StructureKind, yaw_pose

#: Seed ranges per split (inclusive start, exclusive end).
SPLITS = {"train": (0, 5000), "val": (5000, 6000), "test": (6000, 7000)}

WALL_T = 0.12
DOOR_OPENING = 0.92
DOOR_LEAF = 0.88
DOOR_HEIGHT = 2.05
FURNITURE_LIFT = 0.005  # furniture floats 5 mm above the floor so nothing is coplanar with it
CATEGORIES = ("straight_chair", "breakfast_table", "picture", "bottom_cabinet", "cushion", "sofa", "bed", "shelf",
              "sink", "toilet", "stool", "standing_tv", "shower", "bathtub", "countertop")


def split_of(seed: int) -> str:
    for name, (a, b) in SPLITS.items():
        if a <= seed < b:
            return name
    return "extra"


def seeds_for(split: str) -> range:
    if split not in SPLITS:
        raise SceneSpecError(f"unknown split '{split}'; use one of {', '.join(SPLITS)}")
    return range(*SPLITS[split])


def box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    m = trimesh.creation.box(extents=hi - lo)
    m.apply_translation((lo + hi) / 2)
    return m


@dataclass
class Rect:
    x0: float
    y0: float
    x1: float
    y1: float

    @property
    def w(self):
        return self.x1 - self.x0

    @property
    def h(self):
        return self.y1 - self.y0

    @property
    def area(self):
        return self.w * self.h

    def inset(self, d):
        return Rect(self.x0 + d, self.y0 + d, self.x1 - d, self.y1 - d)

    def overlaps(self, o: "Rect", gap=0.0):
        return (self.x0 < o.x1 + gap and o.x0 < self.x1 + gap and self.y0 < o.y1 + gap and o.y0 < self.y1 + gap)

    def inside(self, o: "Rect"):
        eps = 1e-9
        return (self.x0 >= o.x0 - eps and self.x1 <= o.x1 + eps and self.y0 >= o.y0 - eps and self.y1 <= o.y1 + eps)

    def polygon(self):
        return np.array([(self.x0, self.y0), (self.x1, self.y0), (self.x1, self.y1), (self.x0, self.y1)])


@dataclass
class Opening:
    center: float  # along the wall segment
    width: float
    z0: float
    z1: float
    kind: str  # "door" or "window"


@dataclass
class Segment:
    """A wall centre line, horizontal (axis 0: along x at y=c) or vertical (axis 1: along y at x=c)."""

    axis: int
    c: float
    a: float
    b: float
    exterior: bool
    openings: list = field(default_factory=list)


@dataclass
class RoomPlan:
    name: str
    type: str
    rect: Rect  # wall centre lines
    band: str
    kitchenette: bool = False
    blocked: list = field(default_factory=list)  # rects furniture must avoid
    window_zones: list = field(default_factory=list)
    wall_gaps: list = field(default_factory=list)  # (side, a, b) intervals of openings along walls

    @property
    def interior(self) -> Rect:
        return self.rect.inset(WALL_T / 2)


# ------------------------------------------------------------------------------------------------------------
def _partition(rng, total, k, lo):
    """k widths >= lo summing to total."""
    spare = total - k * lo
    w = rng.dirichlet(np.full(k, 3.0)) * spare
    return lo + w


def _plan_layout(rng: np.random.Generator, n_rooms: int):
    rooms: list[RoomPlan] = []
    if n_rooms >= 5:
        k = n_rooms - 1
        k_top = k // 2 + (int(rng.integers(0, 2)) if k % 2 else 0)
        k_bot = k - k_top
        cw = rng.uniform(1.25, 1.5)
        d_top, d_bot = rng.uniform(3.4, 5.0), rng.uniform(3.4, 5.5)
        W = float(np.sum(rng.uniform(2.8, 5.0, max(k_top, k_bot))))
        bands = {"bot": (0.0, d_bot, k_bot), "top": (d_bot + cw, d_bot + cw + d_top, k_top)}
        corridor = Rect(0.0, d_bot, W, d_bot + cw)
    else:
        k_bot = n_rooms - 1
        d_top, d_bot = rng.uniform(4.0, 5.5), rng.uniform(3.4, 5.0)
        W = float(np.sum(rng.uniform(2.9, 4.5, k_bot)))
        bands = {"bot": (0.0, d_bot, k_bot), "top": (d_bot, d_bot + d_top, 0)}
        corridor = None
    D = max(b[1] for b in bands.values())
    # keep the floor area within 50..250 m^2 by stretching the width
    area = W * D
    if area < 58:
        W *= 58 / area
    elif area > 235:
        W *= 235 / area
    for band, (y0, y1, k) in bands.items():
        if k == 0:
            rooms.append(RoomPlan("living room", "living room", Rect(0, y0, W, y1), band))
            continue
        widths = _partition(rng, W, k, 2.5)
        xs = np.concatenate([[0.0], np.cumsum(widths)])
        xs[-1] = W
        for i in range(k):
            rooms.append(RoomPlan(f"{band}{i}", "", Rect(float(xs[i]), y0, float(xs[i + 1]), y1), band))
    if corridor is not None:
        rooms.append(RoomPlan("corridor", "corridor", corridor, "mid"))
    return rooms, W, D


def _assign_types(rng, rooms: list[RoomPlan], n_rooms: int):
    free = [r for r in rooms if not r.type]
    by_area = sorted(free, key=lambda r: r.rect.area)
    bath = by_area[0]
    bath.type = "bathroom"
    if n_rooms >= 5:
        living = by_area[-1]
        living.type = "living room"
        neighbours = [r for r in free if not r.type and r.band == living.band
                      and (abs(r.rect.x0 - living.rect.x1) < 1e-9 or abs(r.rect.x1 - living.rect.x0) < 1e-9)]
        kitchen = neighbours[0] if neighbours else sorted([r for r in free if not r.type],
                                                          key=lambda r: r.rect.area)[0]
        kitchen.type = "kitchen"
    elif n_rooms == 4:
        [r for r in by_area if not r.type][0].type = "kitchen"
    else:
        [r for r in rooms if r.type == "living room"][0].kitchenette = True
    for r in free:
        if not r.type:
            r.type = "bedroom"
    counts: dict[str, int] = {}
    for r in sorted(rooms, key=lambda r: (r.rect.y0, r.rect.x0)):
        counts[r.type] = counts.get(r.type, 0) + 1
    seen: dict[str, int] = {}
    for r in sorted(rooms, key=lambda r: (r.rect.y0, r.rect.x0)):
        seen[r.type] = seen.get(r.type, 0) + 1
        r.name = r.type if counts[r.type] == 1 else f"{r.type} {seen[r.type]}"


def _segments(rooms: list[RoomPlan], W: float, D: float) -> list[Segment]:
    segs = [Segment(0, 0.0, 0.0, W, True), Segment(0, D, 0.0, W, True),
            Segment(1, 0.0, 0.0, D, True), Segment(1, W, 0.0, D, True)]
    # inner horizontal walls only: the outer ones (y = 0 and D) are above (a set difference binds tighter than a
    # union: without the brackets a second, opening-less wall at y = 0 covered the south windows)
    ys = sorted(({r.rect.y0 for r in rooms} | {r.rect.y1 for r in rooms}) - {0.0, D})
    for y in ys:
        segs.append(Segment(0, y, 0.0, W, False))
    for r in rooms:
        if r.rect.x1 < W - 1e-9:
            segs.append(Segment(1, r.rect.x1, r.rect.y0, r.rect.y1, False))
    return segs


def _find_segment(segs, axis, c, a, b):
    for s in segs:
        if s.axis == axis and abs(s.c - c) < 1e-9 and s.a <= a + 1e-9 and b <= s.b + 1e-9:
            return s
    raise AssertionError("no wall segment for a shared edge")  # pragma: no cover - layout invariant


def _side_of(room: RoomPlan, axis: int, c: float) -> str:
    if axis == 0:
        return "S" if abs(room.rect.y0 - c) < 1e-9 else "N"
    return "W" if abs(room.rect.x0 - c) < 1e-9 else "E"


def _add_door(rng, segs, doors, a: RoomPlan, b: RoomPlan, swing_into: RoomPlan):
    """A door between rooms a and b on their shared edge."""
    ra, rb = a.rect, b.rect
    if abs(ra.y1 - rb.y0) < 1e-9 or abs(rb.y1 - ra.y0) < 1e-9:
        axis, c = 0, (ra.y1 if abs(ra.y1 - rb.y0) < 1e-9 else ra.y0)
        lo, hi = max(ra.x0, rb.x0), min(ra.x1, rb.x1)
    else:
        axis, c = 1, (ra.x1 if abs(ra.x1 - rb.x0) < 1e-9 else ra.x0)
        lo, hi = max(ra.y0, rb.y0), min(ra.y1, rb.y1)
    margin = WALL_T / 2 + 0.2 + DOOR_OPENING / 2
    if hi - lo < 2 * margin:
        return False
    center = float(rng.uniform(lo + margin, hi - margin))
    seg = _find_segment(segs, axis, c, lo, hi)
    seg.openings.append(Opening(center, DOOR_OPENING, 0.0, DOOR_HEIGHT, "door"))
    # hinge at one jamb; the leaf turns into `swing_into`
    hinge_end = int(rng.integers(0, 2))
    jamb = center - DOOR_OPENING / 2 + 0.02 if hinge_end == 0 else center + DOOR_OPENING / 2 - 0.02
    hinge = (jamb, c) if axis == 0 else (c, jamb)
    if axis == 0:
        closed_yaw = 0.0 if hinge_end == 0 else 180.0
    else:
        closed_yaw = 90.0 if hinge_end == 0 else -90.0
    r = swing_into.rect
    normal = np.array([0.0, 1.0 if r.y0 >= c - 1e-9 else -1.0]) if axis == 0 else \
        np.array([1.0 if r.x0 >= c - 1e-9 else -1.0, 0.0])
    th = math.radians(closed_yaw)
    swing = 1 if (-math.sin(th) * normal[0] + math.cos(th) * normal[1]) > 0 else -1
    doors.append(dict(hinge=hinge, closed_yaw=closed_yaw, swing=swing, rooms=(a.name, b.name)))
    # keep the swing area and the approach on the other side clear of furniture
    for room, depth in ((a, DOOR_LEAF + 0.3 if room_is(a, swing_into) else 0.9),
                        (b, DOOR_LEAF + 0.3 if room_is(b, swing_into) else 0.9)):
        side = _side_of(room, axis, c)
        half = DOOR_OPENING / 2 + 0.2
        if axis == 0:
            y0, y1 = (c, c + depth) if side == "S" else (c - depth, c)
            room.blocked.append(Rect(center - half, y0, center + half, y1))
        else:
            x0, x1 = (c, c + depth) if side == "W" else (c - depth, c)
            room.blocked.append(Rect(x0, center - half, x1, center + half))
        room.wall_gaps.append((side, center - half, center + half))
    return True


def room_is(a, b):
    return a is b


def _add_windows(rng, segs, rooms: list[RoomPlan], W, D):
    for room in rooms:
        if room.type == "corridor":
            continue
        r = room.rect
        edges = []
        if abs(r.y0) < 1e-9:
            edges.append((0, 0.0, r.x0, r.x1, "S"))
        if abs(r.y1 - D) < 1e-9:
            edges.append((0, D, r.x0, r.x1, "N"))
        if abs(r.x0) < 1e-9:
            edges.append((1, 0.0, r.y0, r.y1, "W"))
        if abs(r.x1 - W) < 1e-9:
            edges.append((1, W, r.y0, r.y1, "E"))
        if not edges:
            continue
        edges.sort(key=lambda e: e[3] - e[2], reverse=True)
        n_win = 2 if room.type == "living room" and len(edges) > 1 else 1
        for axis, c, lo, hi, side in edges[:n_win]:
            span = hi - lo - WALL_T - 0.6
            width = min(0.6 if room.type == "bathroom" else 1.6, span)
            if width < 0.5:
                continue
            center = float(rng.uniform(lo + WALL_T / 2 + 0.3 + width / 2, hi - WALL_T / 2 - 0.3 - width / 2))
            z0 = 1.4 if room.type == "bathroom" else 0.9
            seg = _find_segment(segs, axis, c, lo, hi)
            seg.openings.append(Opening(center, width, z0, 2.1, "window"))
            depth = 0.45
            if axis == 0:
                y0, y1 = (c, c + depth) if side == "S" else (c - depth, c)
                room.window_zones.append(Rect(center - width / 2, y0, center + width / 2, y1))
            else:
                x0, x1 = (c, c + depth) if side == "W" else (c - depth, c)
                room.window_zones.append(Rect(x0, center - width / 2, x1, center + width / 2))
            room.wall_gaps.append((side, center - width / 2 - 0.05, center + width / 2 + 0.05))


def _wall_parts(segs: list[Segment], H: float, mapping: CategoryMapping) -> list[StaticPart]:
    parts = []
    wall_mat, glass_mat = mapping.material_for("wall"), mapping.material_for("window")
    t = WALL_T / 2
    for si, s in enumerate(segs):
        ops = sorted(s.openings, key=lambda o: o.center)
        cuts = [s.a - t]
        pieces = []  # (a, b, z0, z1, kind)
        for o in ops:
            a, b = o.center - o.width / 2, o.center + o.width / 2
            pieces.append((cuts[-1], a, 0.0, H, "wall"))
            if o.z0 > 0:
                pieces.append((a, b, 0.0, o.z0, "wall"))
            if o.z1 < H:
                pieces.append((a, b, o.z1, H, "wall"))
            if o.kind == "window":
                pieces.append((a, b, o.z0, o.z1, "glass"))
            cuts.append(b)
        pieces.append((cuts[-1], s.b + t, 0.0, H, "wall"))
        for pi, (a, b, z0, z1, kind) in enumerate(pieces):
            if b - a < 1e-6:
                continue
            th = t if kind == "wall" else 0.005
            if s.axis == 0:
                mesh = box((a, s.c - th, z0), (b, s.c + th, z1))
            else:
                mesh = box((s.c - th, a, z0), (s.c + th, b, z1))
            if kind == "wall":
                parts.append(StaticPart(f"wall_{si}_{pi}", StructureKind.WALL, "wall", wall_mat, mesh))
            else:
                parts.append(StaticPart(f"window_{si}_{pi}", StructureKind.WINDOW, "window", glass_mat, mesh))
    return parts


def _floor_quad(r: Rect, z: float, up: bool) -> trimesh.Trimesh:
    v = np.array([(r.x0, r.y0, z), (r.x1, r.y0, z), (r.x1, r.y1, z), (r.x0, r.y1, z)])
    faces = [[0, 1, 2], [0, 2, 3]] if up else [[0, 2, 1], [0, 3, 2]]
    return trimesh.Trimesh(v, faces, process=False)


# --- furniture ----------------------------------------------------------------------------------------------
# (category, (width along wall, depth, height), placement, required)
FURNITURE = {
    "living room": [("sofa", (2.0, 0.9, 0.85), "wall", True), ("standing_tv", (1.2, 0.45, 1.2), "wall", True),
                    ("shelf", (0.9, 0.35, 1.8), "wall", False), ("stool", (0.4, 0.4, 0.45), "free", False),
                    ("picture", (0.9, 0.03, 0.6), "hang", False), ("cushion", (0.45, 0.45, 0.15), "on:sofa", False)],
    "kitchen": [("countertop", (2.0, 0.6, 0.9), "wall", True), ("sink", (0.6, 0.6, 0.9), "wall", True),
                ("bottom_cabinet", (0.8, 0.6, 0.9), "wall", False),
                ("breakfast_table", (1.2, 0.8, 0.75), "center", False),
                ("straight_chair", (0.45, 0.45, 0.9), "chair", False),
                ("straight_chair", (0.45, 0.45, 0.9), "chair", False), ("stool", (0.4, 0.4, 0.65), "free", False)],
    "bedroom": [("bed", (1.5, 2.0, 0.5), "wall", True), ("bottom_cabinet", (0.45, 0.4, 0.5), "wall", False),
                ("shelf", (0.8, 0.35, 1.8), "wall", False), ("straight_chair", (0.45, 0.45, 0.9), "free", False),
                ("picture", (0.7, 0.03, 0.5), "hang", False), ("cushion", (0.5, 0.35, 0.15), "on:bed", False)],
    "bathroom": [("shower", (0.9, 0.9, 2.0), "corner", True), ("toilet", (0.4, 0.65, 0.8), "wall", True),
                 ("sink", (0.6, 0.45, 0.85), "wall", True), ("bathtub", (1.7, 0.75, 0.55), "wall", False)],
    "corridor": [("picture", (0.6, 0.03, 0.45), "hang", False)],
}
KITCHENETTE = [("countertop", (1.8, 0.6, 0.9), "wall", True), ("sink", (0.6, 0.6, 0.9), "wall", True),
               ("bottom_cabinet", (0.8, 0.6, 0.9), "wall", False),
               ("breakfast_table", (1.1, 0.75, 0.75), "center", False),
               ("straight_chair", (0.45, 0.45, 0.9), "chair", False)]

_SIDE_YAW = {"S": 0.0, "N": 180.0, "W": -90.0, "E": 90.0}


@dataclass
class Placed:
    category: str
    rect: Rect
    z0: float
    h: float
    yaw: float
    required: bool
    room: str


def _footprint_on_wall(inner: Rect, side: str, pos: float, w: float, d: float) -> Rect:
    if side == "S":
        return Rect(pos, inner.y0, pos + w, inner.y0 + d)
    if side == "N":
        return Rect(pos, inner.y1 - d, pos + w, inner.y1)
    if side == "W":
        return Rect(inner.x0, pos, inner.x0 + d, pos + w)
    return Rect(inner.x1 - d, pos, inner.x1, pos + w)


def _furnish(rng, room: RoomPlan) -> list[Placed]:
    inner = room.interior.inset(0.01)
    placed: list[Placed] = []
    items = list(FURNITURE.get(room.type, []))
    if room.kitchenette:
        items = items[:2] + KITCHENETTE + items[2:]

    def free(rect: Rect, h: float) -> bool:
        if not rect.inside(inner):
            return False
        if any(rect.overlaps(b) for b in room.blocked):
            return False
        if h > 0.85 and any(rect.overlaps(z) for z in room.window_zones):
            return False
        return not any(p.z0 < 0.5 and rect.overlaps(p.rect, 0.05) for p in placed)

    for cat, (w, d, h), how, required in items:
        ok = _try_place(rng, room, inner, placed, free, cat, w * rng.uniform(0.9, 1.1), d, h, how, required)
        if ok is None and required:  # fall back: any wall, a size smaller
            ok = _try_place(rng, room, inner, placed, free, cat, w * 0.85, d * 0.9, h,
                            "wall" if how == "corner" else how, required)
        if ok is not None:
            placed.append(ok)
    return placed


def _try_place(rng, room, inner, placed, free, cat, w, d, h, how, required):
    ok = None
    for _ in range(80):
        if how in ("wall", "corner", "hang"):
            side = str(rng.choice(["S", "N", "W", "E"]))
            along = inner.w if side in "SN" else inner.h
            start = inner.x0 if side in "SN" else inner.y0
            if along < w:
                continue
            if how == "corner":
                pos = start if rng.random() < 0.5 else start + along - w
            else:
                pos = start + rng.uniform(0, along - w)
            if how == "hang":
                if any(s == side and pos < b and a < pos + w for s, a, b in room.wall_gaps):
                    continue
                rect = _footprint_on_wall(inner, side, pos, w, d)
                if any(p.h + p.z0 > 1.2 and rect.overlaps(p.rect, 0.02) for p in placed):
                    continue
                ok = Placed(cat, rect, float(rng.uniform(1.2, 1.5)), h, _SIDE_YAW[side], required, room.name)
                break
            rect = _footprint_on_wall(inner, side, pos, w, d)
            if free(rect, h):
                ok = Placed(cat, rect, FURNITURE_LIFT, h, _SIDE_YAW[side], required, room.name)
                break
        elif how in ("center", "free"):
            margin = 0.75 if how == "center" else 0.3
            if inner.w < w + 2 * margin or inner.h < d + 2 * margin:
                break
            x = rng.uniform(inner.x0 + margin, inner.x1 - margin - w)
            y = rng.uniform(inner.y0 + margin, inner.y1 - margin - d)
            rect = Rect(x, y, x + w, y + d)
            if free(rect, h):
                ok = Placed(cat, rect, FURNITURE_LIFT, h, 0.0, required, room.name)
                break
        elif how == "chair":
            tables = [p for p in placed if p.category == "breakfast_table"]
            if not tables:
                break
            t = tables[0].rect
            cx = rng.uniform(t.x0 + w / 2, t.x1 - w / 2)
            top = rng.random() < 0.5
            y0 = t.y1 + 0.08 if top else t.y0 - 0.08 - d
            rect = Rect(cx - w / 2, y0, cx + w / 2, y0 + d)
            if free(rect, h):
                ok = Placed(cat, rect, FURNITURE_LIFT, h, 180.0 if top else 0.0, required, room.name)
                break
        elif how.startswith("on:"):
            bases = [p for p in placed if p.category == how[3:]]
            if not bases:
                break
            b = bases[0].rect
            if b.w < w or b.h < d:
                break
            x = rng.uniform(b.x0, b.x1 - w)
            y = rng.uniform(b.y0, b.y1 - d)
            ok = Placed(cat, Rect(x, y, x + w, y + d), bases[0].z0 + bases[0].h, h, 0.0, False, room.name)
            break
    return ok


def _object_for(p: Placed, index: int, mapping: CategoryMapping, rng: np.random.Generator) -> SceneObject:
    cx, cy = (p.rect.x0 + p.rect.x1) / 2, (p.rect.y0 + p.rect.y1) / 2
    if abs(p.yaw) == 90.0:
        w, d = p.rect.h, p.rect.w
    else:
        w, d = p.rect.w, p.rect.h
    mesh = box((-w / 2, -d / 2, 0.0), (w / 2, d / 2, p.h))
    movable = p.category in ("cushion", "stool", "straight_chair", "picture")
    return SceneObject(f"{p.category}_{index}", p.category, mapping.material_for(p.category), mesh,
                       yaw_pose(cx, cy, p.z0, p.yaw), movable=movable, room=p.room,
                       parts=furniture.build(p.category, w, d, p.h, rng))


def _look_rng(seed: int, category: str, index: int) -> np.random.Generator:
    """The Generator of an object's look (style, proportions, colours): its own stream, so the layout's draws (and
    every home's plan) do not change with the furniture builders."""
    return np.random.default_rng([seed, 0x100C, sum(map(ord, category)), index])


# ------------------------------------------------------------------------------------------------------------
def generate_apartment(seed: int = 0, mapping: CategoryMapping | None = None, spec: str | None = None) -> Scene:
    """The procedural home for ``seed`` (deterministic)."""
    if seed < 0:
        raise SceneSpecError(f"apartment seed must be >= 0, got {seed}")
    mapping = mapping or MAPPINGS["builtin"]
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x50A1C]))
    n_rooms = int(rng.integers(3, 9))
    H = float(rng.uniform(2.5, 2.8))
    plans, W, D = _plan_layout(rng, n_rooms)
    _assign_types(rng, plans, n_rooms)
    segs = _segments(plans, W, D)
    door_specs: list[dict] = []
    corridor = next((r for r in plans if r.type == "corridor"), None)
    hub = corridor or next(r for r in plans if r.type == "living room")
    for r in plans:
        if r is hub:
            continue
        if not _add_door(rng, segs, door_specs, r, hub, swing_into=r):  # pragma: no cover - widths >= 2.5 m
            raise AssertionError("room too narrow for a door")
    if corridor is not None:
        living = next(r for r in plans if r.type == "living room")
        kitchen = next(r for r in plans if r.type == "kitchen")
        if kitchen.band == living.band and (abs(kitchen.rect.x0 - living.rect.x1) < 1e-9
                                            or abs(kitchen.rect.x1 - living.rect.x0) < 1e-9):
            _add_door(rng, segs, door_specs, kitchen, living, swing_into=kitchen)
    _add_windows(rng, segs, plans, W, D)

    static = _wall_parts(segs, H, mapping)
    rooms = []
    for r in plans:
        inner = r.interior
        static.append(StaticPart(f"floor {r.name}", StructureKind.FLOOR, "floor", mapping.material_for("floor"),
                                 _floor_quad(inner, 0.0, True), room=r.name))
        static.append(StaticPart(f"ceiling {r.name}", StructureKind.CEILING, "ceiling",
                                 mapping.material_for("ceiling"), _floor_quad(inner, H, False), room=r.name))
        rooms.append(Room(r.name, r.type, inner.polygon(), 0.0, H))
    for si, s in enumerate(segs):  # thresholds: floor and ceiling inside door openings
        for oi, o in enumerate(s.openings):
            if o.kind != "door":
                continue
            a, b = o.center - o.width / 2, o.center + o.width / 2
            r = Rect(a, s.c - WALL_T / 2, b, s.c + WALL_T / 2) if s.axis == 0 else \
                Rect(s.c - WALL_T / 2, a, s.c + WALL_T / 2, b)
            static.append(StaticPart(f"threshold_{si}_{oi}", StructureKind.FLOOR, "floor",
                                     mapping.material_for("floor"), _floor_quad(r, 0.0, True)))

    doors = []
    for i, d in enumerate(door_specs):
        leaf = box((0.0, -0.02, FURNITURE_LIFT), (DOOR_LEAF, 0.02, 2.02))
        doors.append(Door(f"door_{i}", "door", mapping.material_for("door"), leaf, movable=False,
                          hinge=d["hinge"], closed_yaw=d["closed_yaw"], swing=d["swing"], open_fraction=1.0,
                          rooms=d["rooms"], width=DOOR_LEAF,
                          parts=tuple(furniture.door(DOOR_LEAF, 0.04, 2.02, _look_rng(seed, "door", i),
                                                     z0=FURNITURE_LIFT))))
    placed: list[Placed] = []
    for r in plans:
        placed.extend(_furnish(rng, r))

    def build(items):
        counts: dict[str, int] = {}
        objs = []
        for p in items:
            k = counts.get(p.category, 0)
            objs.append(_object_for(p, k, mapping, _look_rng(seed, p.category, k)))
            counts[p.category] = counts.get(p.category, 0) + 1
        return Scene(f"apartment {seed}", static, doors + objs, rooms, spec=spec or f"builtin:apartment?seed={seed}",
                     mapping_name=mapping.name, metadata={"seed": seed, "split": split_of(seed),
                                                          "generator": "sonicverse apartment v1"})

    scene = build(placed)
    # navigability: drop optional furniture until every room is reachable (rarely needed)
    from sonicverse_core.geometry.navgrid import NavGrid

    for _ in range(len(placed) + 1):
        grid = NavGrid(scene)
        bad = grid.unreachable_rooms()
        if not bad:
            break
        victims = [p for p in placed if p.room in bad and not p.required and p.z0 < 0.5]
        victims = victims or [p for p in placed if p.room in bad and p.z0 < 0.5]
        if not victims:
            break
        placed.remove(victims[-1])
        placed = [p for p in placed if not (p.z0 >= 0.5 and p.category == "cushion"
                                            and not any(q.rect.overlaps(p.rect) and q is not p and q.z0 < 0.5
                                                        for q in placed))]
        scene = build(placed)
    return scene
