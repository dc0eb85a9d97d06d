"""Rooms for every scene (issue: sound between rooms, item 2): mesh scenes are segmented into rooms at narrow
openings; probes stand in free space at ear height (under a low ceiling too), never inside solid geometry or
outside the enclosure; OBJ objects and groups load as separate parts."""
import numpy as np
import pytest
import trimesh

from sonicverse_core.acoustics.probes import default_probe_positions, enclosed_fraction, scene_probes
from sonicverse_core.scene.spec import load_scene

H = 2.5


def _box(lo, hi):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    m = trimesh.creation.box(extents=hi - lo)
    m.apply_translation((lo + hi) / 2)
    return m


def _write(path, parts):
    sc = trimesh.Scene()
    for name, mesh in parts:
        sc.add_geometry(mesh, node_name=name, geom_name=name)
    sc.export(str(path))
    return str(path)


def _shell(lo, hi, t=0.1):
    """Floor, ceiling and four outer walls (boxes of thickness t) around the interior [lo, hi] x [0, H]."""
    (x0, y0), (x1, y1) = lo, hi
    return [("floor", _box((x0 - t, y0 - t, -t), (x1 + t, y1 + t, 0))),
            ("ceiling", _box((x0 - t, y0 - t, H), (x1 + t, y1 + t, H + t))),
            ("wall_w", _box((x0 - t, y0, 0), (x0, y1, H))), ("wall_e", _box((x1, y0, 0), (x1 + t, y1, H))),
            ("wall_s", _box((x0 - t, y0 - t, 0), (x1 + t, y0, H))), ("wall_n", _box((x0 - t, y1, 0), (x1 + t, y1 + t, H)))]


def _partition(thickness):
    """A wall at x = 4 across the 8 x 4 m room, with a 0.9 m doorway (y 1.55-2.45, 2 m high)."""
    t = max(thickness, 0.0)
    if t > 0:
        return [("wall_p1", _box((4 - t / 2, 0, 0), (4 + t / 2, 1.55, H))),
                ("wall_p2", _box((4 - t / 2, 2.45, 0), (4 + t / 2, 4, H))),
                ("wall_p3", _box((4 - t / 2, 1.55, 2.0), (4 + t / 2, 2.45, H)))]

    def quad(y0, y1, z0, z1):  # a zero-thickness panel (two triangles, seen from both sides)
        v = np.array([[4, y0, z0], [4, y1, z0], [4, y1, z1], [4, y0, z1]], float)
        return trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False)
    return [("wall_p1", quad(0, 1.55, 0, H)), ("wall_p2", quad(2.45, 4, 0, H)), ("wall_p3", quad(1.55, 2.45, 2.0, H))]


def _assert_free_and_enclosed(scene, probes, solids):
    for p in probes:
        for lo, hi in solids:  # never inside solid geometry
            assert not np.all((p >= np.asarray(lo) - 0.05) & (p <= np.asarray(hi) + 0.05)), (p, lo, hi)
    assert np.all(enclosed_fraction(scene, probes) > 0.95)  # inside the enclosure: rays hit walls everywhere


@pytest.mark.parametrize("thickness", [0.0, 0.2])
def test_two_rooms_joined_by_a_doorway_get_one_probe_each_in_free_space(tmp_path, thickness):
    path = _write(tmp_path / f"two_{thickness}.glb", _shell((0, 0), (8, 4)) + _partition(thickness))
    scene = load_scene(path)
    assert len(scene.rooms) == 2, [r.name for r in scene.rooms]
    west, east = sorted(scene.rooms, key=lambda r: r.footprint.mean(0)[0])
    assert west.contains(np.array([[2.0, 2.0]]))[0] and east.contains(np.array([[6.0, 2.0]]))[0]
    assert not west.contains(np.array([[6.0, 2.0]]))[0]
    assert 13 < west.area < 16.5 and 13 < east.area < 16.5  # each about 4 x 4 m, less the walls
    assert west.z_ceiling == pytest.approx(H, abs=0.06)
    probes = default_probe_positions(scene)
    assert len(probes) == 2 and np.allclose(probes[:, 2], 1.5)
    assert sorted(np.sign(probes[:, 0] - 4)) == [-1, 1]  # one on each side of the partition
    solids = [((4 - thickness / 2, 0, 0), (4 + thickness / 2, 1.55, H)),
              ((4 - thickness / 2, 2.45, 0), (4 + thickness / 2, 4, H))]
    _assert_free_and_enclosed(scene, probes, solids)
    assert scene_probes(scene) is not None


def test_an_l_shaped_room_is_one_room_with_its_probe_inside(tmp_path):
    # interior: [0, 6] x [0, 6] without the square [3, 6] x [3, 6], walled with boxes
    parts = [("floor", _box((-0.1, -0.1, -0.1), (6.1, 6.1, 0))), ("ceiling", _box((-0.1, -0.1, H), (6.1, 6.1, H + 0.1))),
             ("wall_1", _box((-0.1, 0, 0), (0, 6, H))), ("wall_2", _box((-0.1, -0.1, 0), (6.1, 0, H))),
             ("wall_3", _box((6, 0, 0), (6.1, 3, H))), ("wall_4", _box((3, 6, 0), (3.1, 6.1, H))),
             ("wall_5", _box((-0.1, 6, 0), (3.1, 6.1, H))), ("wall_6", _box((3, 3, 0), (6.1, 3.1, H))),
             ("column", _box((3.1, 3.1, 0), (6, 6, H)))]  # the missing quadrant is solid
    scene = load_scene(_write(tmp_path / "l.glb", parts))
    assert len(scene.rooms) == 1
    probes = default_probe_positions(scene)
    assert len(probes) == 1
    _assert_free_and_enclosed(scene, probes, [((3, 3, 0), (6.1, 6.1, H))])
    assert scene.rooms[0].contains(probes[:, :2])[0]


def test_a_room_lower_than_1_5_m_still_gets_a_probe_under_its_ceiling():
    scene = load_scene("shoebox:6x4x1.2")
    probes = scene_probes(scene)
    assert probes is not None and len(probes) == 1
    assert 0.6 <= probes[0].position[2] <= 0.9 + 1e-6  # float32 once read back from the bake cache


@pytest.mark.parametrize("height", [0.2, 0.4])
def test_a_room_lower_than_the_robot_still_gets_a_probe_and_a_reverb(height):
    """The robot's grid finds no floor under a ceiling lower than the robot (0.5 m: its floor rays start above it),
    so such a room had no probe, no early reflections and no late reverb (session 67)."""
    from sonicverse_core.acoustics.renderer import AcousticRenderer

    scene = load_scene(f"shoebox:3x3x{height}")
    probes = scene_probes(scene)
    assert probes is not None and len(probes) == 1
    p = probes[0].position
    assert p[2] == pytest.approx(height / 2, abs=1e-6) and np.allclose(p[:2], 1.5, atol=0.1)  # the middle
    _assert_free_and_enclosed(scene, [p], [])
    assert {"early_reflections", "late_reverb"} <= set(AcousticRenderer(scene, probes=probes).subsystems)


def test_a_floor_plan_too_large_for_the_navigation_grid_still_gets_its_probe():
    """A 1000 x 1000 m hall needs 400M cells of the robot's 5 cm grid (refused, with advice); its probe is placed
    on a coarser floor grid instead, in free space at ear height, near the middle."""
    from sonicverse_core.errors import ConfigError
    from sonicverse_core.geometry.navgrid import NavGrid

    scene = load_scene("shoebox:1000x1000x3")
    with pytest.raises(ConfigError, match=r"NavConfig\(cell=0\.2[0-9]\)"):
        NavGrid(scene)
    probes = default_probe_positions(scene)
    assert probes.shape == (1, 3) and probes[0, 2] == pytest.approx(1.5)
    assert np.allclose(probes[0, :2], 500, atol=1.0)
    _assert_free_and_enclosed(scene, probes, [])
    with pytest.raises(ConfigError, match="no cell up to 0.5 m fits it"):  # 3 km: too large for any grid
        default_probe_positions(load_scene("shoebox:3000x3000x3"))


def test_obj_objects_and_groups_load_as_separate_parts(tmp_path):
    obj = tmp_path / "two.obj"
    lines = ["mtllib none.mtl"]
    v = 0
    for name, x in (("o wall_a", 0.0), ("o wall_b", 5.0), ("g chair_1", 2.0), ("g chair_2", 3.0)):
        lines.append(name)
        lines.append("usemtl Uniform")
        for dx, dy, dz in ((0, 0, 0), (0.1, 0, 0), (0.1, 4, 0), (0, 4, 0), (0, 0, 2.5), (0.1, 0, 2.5), (0.1, 4, 2.5),
                           (0, 4, 2.5)):
            lines.append(f"v {x + dx} {dy} {dz}")
        for f in ((1, 2, 3), (1, 3, 4), (5, 7, 6), (5, 8, 7), (1, 5, 6), (1, 6, 2), (2, 6, 7), (2, 7, 3), (3, 7, 8),
                  (3, 8, 4), (4, 8, 5), (4, 5, 1)):
            lines.append("f " + " ".join(str(v + i) for i in f))
        v += 8
    obj.write_text("\n".join(lines) + "\n")
    scene = load_scene(str(obj))
    names = sorted([p.name for p in scene.static] + [o.name for o in scene.objects])
    assert len(names) == 4, names  # before: merged into one part by their shared material
