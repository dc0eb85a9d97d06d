import numpy as np
import pytest

from sonicverse_core.errors import ConfigError
from sonicverse_core.geometry.navgrid import NavGrid
from sonicverse_core.geometry.raycast import RayCaster, SceneRayCaster
from sonicverse_core.scene.spec import load_scene


def test_embree_agrees_with_numpy_reference(apartment, rng):
    mesh = apartment.static_mesh()
    lo, hi = apartment.bounds
    o = rng.uniform(lo + 0.1, hi - 0.1, (1500, 3))
    d = rng.normal(size=(1500, 3))
    e = RayCaster(mesh, "embree").first_hit(o, d)
    n = RayCaster(mesh, "numpy").first_hit(o, d)
    same = e.hit == n.hit
    assert same.mean() > 0.995  # grazing edge hits may differ
    both = e.hit & n.hit
    close = np.abs(e.distance[both] - n.distance[both]) < 1e-3
    assert close.mean() > 0.995
    # where both hit the same face, the material is the same
    sf = both & (e.face == n.face)
    assert sf.mean() > 0.95
    np.testing.assert_array_equal(e.material[sf], n.material[sf])


def test_first_hit_in_shoebox_is_exact():
    s = load_scene("shoebox:6x4x3?floor=Marble")
    c = SceneRayCaster(s)
    h = c.first_hit([[1, 1, 1.5]] * 3, [[0, 0, -1], [1, 0, 0], [0, -1, 0]])
    np.testing.assert_allclose(h.distance, [1.5, 5.0, 1.0], atol=1e-5)
    assert s.static_mesh().part_names[h.part[0]] == "floor"
    np.testing.assert_allclose(h.normal[0], [0, 0, 1], atol=1e-9)  # floor normal points into the room
    with pytest.raises(ConfigError):
        c.first_hit([[np.nan, 0, 0]], [[1, 0, 0]])


def test_crossings_through_walls_and_doors(apartment):
    s = load_scene("builtin:apartment?seed=3")
    c = SceneRayCaster(s)
    living = next(r for r in s.rooms if r.type == "living room")
    bath = next(r for r in s.rooms if r.type == "bathroom")
    a = np.r_[living.footprint.mean(0), 1.5]
    b = np.r_[bath.footprint.mean(0), 1.5]
    cr = c.crossings([a], [b], include_dynamic=False)
    assert len(cr.ray) >= 2 and np.all(np.diff(cr.distance) > 0)
    assert not c.line_of_sight([a], [b])[0]
    # a door closing adds crossings of its leaf in the next query
    door = next(d for d in s.doors if bath.name in d.rooms)
    door.set_open(0.0)
    s.touch()
    mid = np.r_[np.array(door.hinge) + 0.44 * np.array([np.cos(np.radians(door.closed_yaw)),
                                                           np.sin(np.radians(door.closed_yaw))]), 1.0]
    n = np.r_[-np.sin(np.radians(door.closed_yaw)), np.cos(np.radians(door.closed_yaw)), 0]
    closed = c.crossings([mid - 0.5 * n], [mid + 0.5 * n])
    assert any(c.part_name(p) == door.name for p in closed.part)
    door.set_open(1.0)
    s.touch()
    opened = c.crossings([mid - 0.5 * n], [mid + 0.5 * n])
    assert len(opened.ray) == 0


def test_geodesic_at_least_euclidean(apartment, rng):
    g = NavGrid(apartment)
    pts = g.sample(rng, 30)
    for a, b in zip(pts[:15], pts[15:]):
        path, length = g.shortest_path(a, b)
        assert np.isfinite(length)
        assert length >= np.linalg.norm(a - b) - 1e-9
        assert np.all(g.is_navigable(path[1:-1], main_only=False)) if len(path) > 2 else True
    field = g.distance_field(pts[0])
    d = g.geodesic_from_field(field, pts[1:])
    assert np.all(d >= np.linalg.norm(pts[1:] - pts[0], axis=1) - g.config.cell)


def test_geodesic_equals_euclidean_in_empty_room():
    g = NavGrid(load_scene("shoebox:6x4x3"))
    a, b = np.array([0.7, 0.6]), np.array([5.2, 3.3])
    path, length = g.shortest_path(a, b)
    assert length == pytest.approx(np.linalg.norm(b - a), abs=1e-9)
    assert len(path) == 2
    field = g.distance_field(b)
    # the 16-neighbour field is within 3% of the straight line
    assert g.geodesic_from_field(field, a[None])[0] == pytest.approx(np.linalg.norm(b - a), rel=0.03)
    # the robot keeps its radius from the walls
    assert not g.is_navigable([[0.1, 2.0]])[0] and g.is_navigable([[3.0, 2.0]])[0]
    assert g.navigable_area == pytest.approx((6 - 2 * 0.205) * (4 - 2 * 0.205), rel=0.06)


def test_sampling_is_seeded(apartment):
    g = NavGrid(apartment)
    a = g.sample(np.random.default_rng(5), 10)
    b = g.sample(np.random.default_rng(5), 10)
    np.testing.assert_array_equal(a, b)
    assert np.all(g.is_navigable(a))


def test_crossings_agree_between_embree_and_the_numpy_reference(apartment):
    """The segment walk's Embree fast path finds the same surfaces, in the same order, as the float64 reference."""
    s = load_scene("builtin:apartment?seed=3")
    e, n = SceneRayCaster(s), SceneRayCaster(s, backend="numpy")
    lo, hi = s.static_mesh().vertices.min(0), s.static_mesh().vertices.max(0)
    rng = np.random.default_rng(7)
    a, b = rng.uniform(lo + 0.1, hi - 0.1, (40, 3)), rng.uniform(lo + 0.1, hi - 0.1, (40, 3))
    ce, cn = e.crossings(a, b), n.crossings(a, b)
    assert len(ce.ray) > 40  # walls, furniture and doors are crossed
    keep = lambda c: np.abs(c.distance - np.linalg.norm(b - a, axis=1)[c.ray]) > 1e-3  # noqa: E731 - not at an end
    ke, kn = keep(ce), keep(cn)
    np.testing.assert_array_equal(ce.ray[ke], cn.ray[kn])  # as many crossings per segment, in segment order
    np.testing.assert_allclose(ce.distance[ke], cn.distance[kn], atol=1e-4)
    meshes = (s.static_mesh(), s.dynamic_mesh())

    def touches(part, dyn, point):  # the crossing point is on (or in) the part's bounds
        m = meshes[int(dyn)]
        v = m.vertices[np.unique(m.faces[m.face_part == part - (e.part_offset() if dyn else 0)])]
        return bool(np.all(point >= v.min(0) - 1e-4) and np.all(point <= v.max(0) + 1e-4))

    for r in range(len(a)):  # the same surfaces, crossing by crossing; where parts touch (walls meeting face to face,
        # parts at one distance) a crossing of their shared plane may name either of them
        se, sn = ce.ray[ke] == r, cn.ray[kn] == r
        oe, on = np.argsort(ce.distance[ke][se], kind="stable"), np.argsort(cn.distance[kn][sn], kind="stable")
        for pe, de, pn, dn, t in zip(ce.part[ke][se][oe], ce.dynamic[ke][se][oe], cn.part[kn][sn][on],
                                     cn.dynamic[kn][sn][on], cn.distance[kn][sn][on]):
            if (pe, de) != (pn, dn):
                point = a[r] + (b[r] - a[r]) / np.linalg.norm(b[r] - a[r]) * t
                assert touches(pe, de, point) and touches(pn, dn, point), (r, pe, pn, t)
        assert sorted(ce.dynamic[ke][ce.ray[ke] == r]) == sorted(cn.dynamic[kn][cn.ray[kn] == r])
