"""Reference rooms for sound between rooms (tests, ``bench fidelity``, and anyone checking the renderer):

- ``builtin:l-room`` an L-shaped room (the square [0, 6] x [0, 6] without its [3, 6] x [3, 6] quarter), 3 m high;
- ``builtin:two-rooms?door=open|closed|sealed`` two 4 x 4 x 3 m rooms side by side, joined at x = 4 by a 0.1 m
  stud partition (``Sheetrock``, 10 kg/m^2) with a 0.9 x 2.1 m doorway in its middle (a hinged ``door`` leaf, 8
  kg/m^2, open or closed), or with no doorway at all (sealed); ``&west=MATERIAL`` / ``&east=MATERIAL`` give that
  room's walls, floor and ceiling one material (a dead room beside a live one: coupled-room decay);
- ``builtin:three-rooms?door=open|closed|sealed`` three such rooms in a row (x in [0, 4], [4, 8], [8, 12]), two
  partitions with a doorway each (``door_w`` between west and middle, ``door_e`` between middle and east);
  ``&west=`` / ``&middle=`` / ``&east=`` give a room one material (a dead hall between two live rooms: more than
  one neighbouring room heard apart).

Walls, floor and ceiling are boxes 0.2 m thick (the partition 0.1 m), so they are solid for rays, rooms, probes
and paths alike. Surfaces: plaster walls, parquet floor, smooth plaster ceiling.
"""
from __future__ import annotations

import numpy as np
import trimesh

from sonicverse_core.errors import SceneSpecError
from sonicverse_core.scene.model import Door, Room, Scene, StaticPart, StructureKind

WALLS, FLOOR, CEILING = "PlasterRough", "ParquetOnConcrete", "PlasterSmooth"
PARTITION, DOOR = "Sheetrock", "WoodPanel"
T = 0.2  # outer walls, floor, ceiling (m)
T_PARTITION = 0.1
DOOR_WIDTH, DOOR_HEIGHT = 0.9, 2.1


def _box(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    m = trimesh.creation.box(extents=hi - lo)
    m.apply_translation((lo + hi) / 2)
    return m


def _shell(x1: float, y1: float, H: float, walls: list, room_of=None) -> list[StaticPart]:
    parts = [StaticPart("floor", StructureKind.FLOOR, "floor", FLOOR, _box((-T, -T, -T), (x1 + T, y1 + T, 0))),
             StaticPart("ceiling", StructureKind.CEILING, "ceiling", CEILING, _box((-T, -T, H), (x1 + T, y1 + T, H + T)))]
    for k, (lo, hi, mat) in enumerate(walls):
        parts.append(StaticPart(f"wall_{k}", StructureKind.WALL, "wall", mat, _box(lo, hi)))
    return parts


def l_room(size: float = 6.0, H: float = 3.0) -> Scene:
    S, h = size, size / 2
    walls = [((-T, -T, 0), (0, S + T, H), WALLS), ((-T, -T, 0), (S + T, 0, H), WALLS),
             ((S, -T, 0), (S + T, h, H), WALLS), ((-T, S, 0), (h, S + T, H), WALLS),
             ((h, h, 0), (S + T, S + T, H), WALLS)]  # the missing quarter, solid
    room = Room("room", "living room", np.array([(0, 0), (S, 0), (S, h), (h, h), (h, S), (0, S)], float), 0.0, H)
    return Scene("l-room", _shell(S, S, H, walls), [], [room], spec="builtin:l-room", mapping_name="explicit")


def two_rooms(door: str = "open", L: float = 8.0, W: float = 4.0, H: float = 3.0, west: str | None = None,
              east: str | None = None) -> Scene:
    if door not in ("open", "closed", "sealed"):
        raise SceneSpecError(f"two-rooms: door must be open, closed or sealed, got '{door}'")
    from sonicverse_core.scene.materials import MATERIALS

    for side, m in (("west", west), ("east", east)):
        if m is not None and m not in MATERIALS:
            raise SceneSpecError(f"two-rooms: unknown {side} material '{m}'; use one of {', '.join(sorted(MATERIALS))}")
    xm, t = L / 2, T_PARTITION / 2
    y0, y1 = W / 2 - DOOR_WIDTH / 2, W / 2 + DOOR_WIDTH / 2
    walls = [((-T, -T, 0), (0, W + T, H), WALLS), ((L, -T, 0), (L + T, W + T, H), WALLS),
             ((-T, -T, 0), (L + T, 0, H), WALLS), ((-T, W, 0), (L + T, W + T, H), WALLS)]
    if door == "sealed":
        walls.append(((xm - t, 0, 0), (xm + t, W, H), PARTITION))
    else:
        walls += [((xm - t, 0, 0), (xm + t, y0, H), PARTITION), ((xm - t, y1, 0), (xm + t, W, H), PARTITION),
                  ((xm - t, y0, DOOR_HEIGHT), (xm + t, y1, H), PARTITION)]
    rooms = [Room("west", "living room", np.array([(0, 0), (xm - t, 0), (xm - t, W), (0, W)], float), 0.0, H),
             Room("east", "bedroom", np.array([(xm + t, 0), (L, 0), (L, W), (xm + t, W)], float), 0.0, H)]
    parts = _shell(L, W, H, walls)
    if west or east:  # each room's own surfaces: the outer shell cut at the partition
        parts = []
        for name, x0, x1, mat in (("west", -T, xm, west), ("east", xm, L + T, east)):
            wm, fm, cm = (mat, mat, mat) if mat else (WALLS, FLOOR, CEILING)
            parts += [StaticPart(f"floor_{name}", StructureKind.FLOOR, "floor", fm, _box((x0, -T, -T), (x1, W + T, 0))),
                      StaticPart(f"ceiling_{name}", StructureKind.CEILING, "ceiling", cm,
                                 _box((x0, -T, H), (x1, W + T, H + T))),
                      StaticPart(f"wall_{name}_s", StructureKind.WALL, "wall", wm, _box((x0, -T, 0), (x1, 0, H))),
                      StaticPart(f"wall_{name}_n", StructureKind.WALL, "wall", wm, _box((x0, W, 0), (x1, W + T, H)))]
        ends = [((-T, 0, 0), (0, W, H), west or WALLS), ((L, 0, 0), (L + T, W, H), east or WALLS)]
        parts += [StaticPart(f"wall_{k}", StructureKind.WALL, "wall", m, _box(lo, hi))
                  for k, (lo, hi, m) in enumerate(ends + walls[4:])]
    objects = []
    if door != "sealed":
        leaf = _box((0.0, -0.02, 0.0), (DOOR_WIDTH, 0.02, DOOR_HEIGHT - 0.01))
        objects.append(Door("door", "door", DOOR, leaf, movable=False, hinge=(xm, y0), closed_yaw=90.0, swing=-1,
                            open_fraction=1.0 if door == "open" else 0.0, rooms=("west", "east"), width=DOOR_WIDTH))
    spec = f"builtin:two-rooms?door={door}" + "".join(f"&{k}={v}" for k, v in (("west", west), ("east", east)) if v)
    return Scene(f"two rooms ({door})", parts, objects, rooms, spec=spec, mapping_name="explicit")


def _rooms_in_a_row(names: list, types: list, door: str, mats: dict, W: float = 4.0, H: float = 3.0,
                    R: float = 4.0) -> tuple[list, list, list]:
    """Rooms of R x W x H m side by side along x, each with its own floor, ceiling and outer walls (``mats[name]``,
    or the defaults), a ``Sheetrock`` partition between neighbours with a 0.9 x 2.1 m doorway in its middle (a
    hinged leaf per doorway) unless sealed: (parts, doors, rooms)."""
    n, t = len(names), T_PARTITION / 2
    L = n * R
    y0, y1 = W / 2 - DOOR_WIDTH / 2, W / 2 + DOOR_WIDTH / 2
    parts, objects, rooms = [], [], []
    for k, name in enumerate(names):
        mat = mats.get(name)
        wm, fm, cm = (mat, mat, mat) if mat else (WALLS, FLOOR, CEILING)
        x0, x1 = (-T if k == 0 else k * R), (L + T if k == n - 1 else (k + 1) * R)
        parts += [StaticPart(f"floor_{name}", StructureKind.FLOOR, "floor", fm, _box((x0, -T, -T), (x1, W + T, 0))),
                  StaticPart(f"ceiling_{name}", StructureKind.CEILING, "ceiling", cm,
                             _box((x0, -T, H), (x1, W + T, H + T))),
                  StaticPart(f"wall_{name}_s", StructureKind.WALL, "wall", wm, _box((x0, -T, 0), (x1, 0, H))),
                  StaticPart(f"wall_{name}_n", StructureKind.WALL, "wall", wm, _box((x0, W, 0), (x1, W + T, H)))]
        lo = k * R + (t if k > 0 else 0.0)
        hi = (k + 1) * R - (t if k < n - 1 else 0.0)
        rooms.append(Room(name, types[k], np.array([(lo, 0), (hi, 0), (hi, W), (lo, W)], float), 0.0, H))
    parts += [StaticPart("wall_end_w", StructureKind.WALL, "wall", mats.get(names[0]) or WALLS,
                         _box((-T, 0, 0), (0, W, H))),
              StaticPart("wall_end_e", StructureKind.WALL, "wall", mats.get(names[-1]) or WALLS,
                         _box((L, 0, 0), (L + T, W, H)))]
    for k in range(1, n):
        xm, tag = k * R, "we"[k - 1] if n == 3 else str(k)
        boxes = ([((xm - t, 0, 0), (xm + t, W, H))] if door == "sealed" else
                 [((xm - t, 0, 0), (xm + t, y0, H)), ((xm - t, y1, 0), (xm + t, W, H)),
                  ((xm - t, y0, DOOR_HEIGHT), (xm + t, y1, H))])
        parts += [StaticPart(f"partition_{tag}_{j}", StructureKind.WALL, "wall", PARTITION, _box(lo, hi))
                  for j, (lo, hi) in enumerate(boxes)]
        if door != "sealed":
            leaf = _box((0.0, -0.02, 0.0), (DOOR_WIDTH, 0.02, DOOR_HEIGHT - 0.01))
            objects.append(Door(f"door_{tag}", "door", DOOR, leaf, movable=False, hinge=(xm, y0), closed_yaw=90.0,
                                swing=-1, open_fraction=1.0 if door == "open" else 0.0,
                                rooms=(names[k - 1], names[k]), width=DOOR_WIDTH))
    return parts, objects, rooms


def three_rooms(door: str = "open", west: str | None = None, middle: str | None = None,
                east: str | None = None) -> Scene:
    """Three 4 x 4 x 3 m rooms in a row (the module docstring)."""
    if door not in ("open", "closed", "sealed"):
        raise SceneSpecError(f"three-rooms: door must be open, closed or sealed, got '{door}'")
    from sonicverse_core.scene.materials import MATERIALS

    mats = {"west": west, "middle": middle, "east": east}
    for side, m in mats.items():
        if m is not None and m not in MATERIALS:
            raise SceneSpecError(f"three-rooms: unknown {side} material '{m}'; use one of "
                                 f"{', '.join(sorted(MATERIALS))}")
    parts, objects, rooms = _rooms_in_a_row(["west", "middle", "east"], ["living room", "hallway", "bedroom"],
                                            door, mats)
    spec = f"builtin:three-rooms?door={door}" + "".join(f"&{k}={v}" for k, v in mats.items() if v)
    return Scene(f"three rooms ({door})", parts, objects, rooms, spec=spec, mapping_name="explicit")
