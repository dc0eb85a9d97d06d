"""The procedural apartment over 200 seeds: reachability, no furniture in walls, doors connect rooms."""
import numpy as np
import pytest

from sonicverse_core.geometry.navgrid import NavGrid
from sonicverse_core.scene.apartment import CATEGORIES, SPLITS, WALL_T, generate_apartment, seeds_for, split_of
from sonicverse_core.scene.model import Door, StructureKind

SEEDS = list(range(0, 140)) + list(range(5000, 5030)) + list(range(6000, 6030))  # 200 seeds over all splits


def _overlap(a, b, tol=1e-6):
    return bool(np.all(np.minimum(a[1], b[1]) - np.maximum(a[0], b[0]) > tol))


@pytest.mark.parametrize("seed", SEEDS)
def test_apartment_invariants(seed):
    s = generate_apartment(seed)
    assert 3 <= len(s.rooms) <= 8
    area = sum(r.area for r in s.rooms)
    assert 50 <= area <= 250, area
    types = {r.type for r in s.rooms}
    assert {"living room", "bathroom", "bedroom"} <= types
    # every room reachable from every other for a 0.18 m robot
    grid = NavGrid(s)
    assert grid.unreachable_rooms() == []
    # no furniture intersects a wall (walls are solid boxes)
    walls = [p.mesh.bounds for p in s.static if p.kind == StructureKind.WALL]
    for o in s.objects:
        if isinstance(o, Door):
            continue
        ob = o.world_bounds()
        assert not any(_overlap(ob, w) for w in walls), (seed, o.name)
        room = next(r for r in s.rooms if r.name == o.room)
        c = ob.mean(0)[:2]
        assert room.contains(c)[0], (seed, o.name)
    # doors connect the rooms they name: the two sides of the closed leaf lie in those rooms
    for d in s.doors:
        d.set_open(0.0)
        mid = np.array(d.hinge) + 0.44 * np.array([np.cos(np.radians(d.closed_yaw)), np.sin(np.radians(d.closed_yaw))])
        n = np.array([-np.sin(np.radians(d.closed_yaw)), np.cos(np.radians(d.closed_yaw))])
        sides = {s.room_at(mid + n * (WALL_T / 2 + 0.1)).name, s.room_at(mid - n * (WALL_T / 2 + 0.1)).name}
        assert sides == set(d.rooms), (seed, d.name)
        d.set_open(1.0)
    # the bathroom has its fixtures, the kitchen its sink and countertop, a bedroom its bed
    by_room = {}
    for o in s.objects:
        by_room.setdefault(next(r.type for r in s.rooms if r.name == o.room) if o.room else None, set()).add(o.category)
    assert {"toilet", "shower", "sink"} <= by_room["bathroom"]
    assert "bed" in by_room["bedroom"]
    kitchen = by_room.get("kitchen", by_room["living room"])
    assert {"sink", "countertop"} <= kitchen


def test_deterministic_and_varied():
    a, b = generate_apartment(42), generate_apartment(42)
    assert a.static_hash() == b.static_hash()
    assert [o.name for o in a.objects] == [o.name for o in b.objects]
    np.testing.assert_array_equal(a.dynamic_mesh().vertices, b.dynamic_mesh().vertices)
    assert len({generate_apartment(s).static_hash() for s in range(10)}) == 10


def test_all_categories_appear_across_homes():
    seen = set()
    for seed in range(10):
        seen |= {o.category for o in generate_apartment(seed).objects}
    assert set(CATEGORIES) <= seen


def test_splits_are_disjoint():
    ranges = [set(seeds_for(k)) for k in SPLITS]
    assert not (ranges[0] & ranges[1]) and not (ranges[0] & ranges[2]) and not (ranges[1] & ranges[2])
    assert split_of(0) == "train" and split_of(5000) == "val" and split_of(6999) == "test"


def test_closing_a_door_cuts_the_room_off():
    s = generate_apartment(3)
    bath = next(r for r in s.rooms if r.type == "bathroom")
    door = next(d for d in s.doors if bath.name in d.rooms)
    s.set_door(door.name, 0.0)
    assert bath.name in NavGrid(s).unreachable_rooms()
    s.set_door(door.name, 1.0)
    assert NavGrid(s).unreachable_rooms() == []
