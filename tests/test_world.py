"""The embodied world: TurtleBot kinematics, collisions without tunnelling, doors, carrying objects, cameras."""
import math

import numpy as np
import pytest

from sonicverse_core.errors import ActionError, PoseError
from sonicverse_core.scene.spec import load_scene
from sonicverse_core.world import RobotConfig, World
from sonicverse_core.world.robot import body_velocity, integrate, wheel_action


def _open(x, y):
    return True


def test_turtlebot_numbers_and_kinematics():
    cfg = RobotConfig()
    assert (cfg.wheel_base, cfg.wheel_radius, cfg.max_speed) == (0.230, 0.035, 0.7)
    assert cfg.max_wheel_omega == pytest.approx(20.0)
    # straight at top speed for 1 s: 0.7 m along the heading
    p, bumped, d = integrate(cfg, np.array([0.0, 0.0, 90.0]), np.array([1.0, 1.0]), 1.0, _open)
    assert np.allclose(p, [0.0, 0.7, 90.0], atol=1e-9) and d == pytest.approx(0.7) and not bumped
    # spin in place: the firmware's 180 deg/s limit, no translation
    p, _, d = integrate(cfg, np.zeros(3), np.array([-1.0, 1.0]), 0.5, _open)
    assert p[2] == pytest.approx(90.0) and np.allclose(p[:2], 0.0) and d == 0.0
    # an arc is integrated exactly: radius v / w, whatever the sub-step count
    v, w = body_velocity(cfg, np.array([0.3, 0.5]))
    p, _, _ = integrate(cfg, np.zeros(3), np.array([0.3, 0.5]), 2.0, _open)
    r = v / w
    assert np.allclose(p[:2], [r * math.sin(w * 2.0), r * (1 - math.cos(w * 2.0))], atol=1e-9)


def test_actions_are_validated_and_clipped():
    assert np.array_equal(wheel_action([2.0, -3.0]), [1.0, -1.0])  # documented clip
    for bad in ([np.nan, 0.0], [0.0, np.inf], [1.0], [[1.0, 2.0, 3.0]], "fast"):
        with pytest.raises(ActionError):
            wheel_action(bad)


@pytest.fixture(scope="module")
def box_world():
    return World(load_scene("shoebox:6x4x3"))


def test_walls_stop_fast_robots_without_tunnelling(box_world):
    w = box_world
    w.place_robot(3.0, 2.0, 0.0)
    for dt in (0.1, 1.0, 5.0):  # 5 s at 0.7 m/s would cross the 6 m room's far wall if tunnelling were possible
        w.place_robot(3.0, 2.0, 0.0)
        for _ in range(int(10 / dt)):  # 7 m of driving: more than the room is long
            w.drive([1.0, 1.0], dt)
            assert w.free(*w.pose[:2])
        assert w.pose[0] < 6.0 - RobotConfig().radius + 1e-9
        assert w.bumped
    # it stopped short of the wall by at most the margins: half a cell of clearance, one cell of quantisation and
    # one sub-step of travel (8 cm with the defaults)
    gap = 6.0 - w.pose[0] - RobotConfig().radius
    assert 0.0 < gap <= 1.5 * w.nav.cell + RobotConfig().substep + 1e-3


def test_robot_slides_along_a_wall(box_world):
    w = box_world
    w.place_robot(5.5, 1.0, 45.0)
    x0 = w.pose[0]
    y_before = w.pose[1]
    for _ in range(20):
        w.drive([1.0, 1.0], 0.1)
    assert w.bumped
    assert w.pose[1] - y_before > 0.5  # kept moving along the wall (+y) after meeting it
    assert w.pose[0] >= x0 - 1e-9
    stop = World(load_scene("shoebox:6x4x3"), RobotConfig(collision="stop"))
    stop.place_robot(5.5, 1.0, 45.0)
    for _ in range(20):
        stop.drive([1.0, 1.0], 0.1)
    assert stop.pose[1] < w.pose[1] - 0.3  # "stop" mode stays where it met the wall


def test_place_robot_rejects_walls_and_nan(box_world):
    with pytest.raises(PoseError):
        box_world.place_robot(0.05, 2.0, 0.0)
    with pytest.raises(PoseError):
        box_world.place_robot(float("nan"), 2.0, 0.0)


@pytest.fixture(scope="module")
def home():
    scene = load_scene("builtin:apartment?seed=6000")
    return World(scene)


def test_doors_close_and_open_the_way(home):
    w = home
    door = w.scene.doors[0]
    a, b = door.rooms
    ra = next(r for r in w.scene.rooms if r.name == a)
    rb = next(r for r in w.scene.rooms if r.name == b)
    rng = np.random.default_rng(0)
    pa = w.grid.sample(rng, 1, room=ra.name)[0]
    pb = w.grid.sample(rng, 1, room=rb.name)[0]
    open_d = w.grid.geodesic_distance(pa, pb)
    assert np.isfinite(open_d)
    w.place_robot(*pa, 0.0)
    w.set_door(door.name, 0.0)
    try:
        closed = w.grid.distance_field(pb)
        d_closed = float(w.grid.geodesic_from_field(closed, pa[None])[0])
        assert d_closed > open_d + 0.5  # the closed door blocks the opening: a detour or no way at all
        assert w.scene.dynamic_version > 0
    finally:
        w.set_door(door.name, 1.0)
    assert w.grid.geodesic_distance(pa, pb) == pytest.approx(open_d, abs=1e-6)


def test_a_door_does_not_swing_into_the_robot(home):
    w = home
    door = w.scene.doors[0]
    # stand where the open leaf will sweep: the middle of the leaf when it is half closed
    w.scene.set_door(door.name, 0.5)
    mid = door.pose[:2, :2] @ np.array([0.45, 0.0]) + door.pose[:2, 3]
    w.scene.set_door(door.name, 1.0)
    w._rebuild()
    if not w.free(*mid):
        pytest.fail("test setup: the door's sweep should be free floor when the door is open")
    w.place_robot(*mid, 0.0)
    with pytest.raises(ActionError, match="in its way"):
        w.set_door(door.name, 0.0)
    assert door.open_fraction == 1.0 and w.free(*w.pose[:2])


def test_pick_carry_place_moves_the_sound(home):
    from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig

    w = home
    w.restore()
    obj = next(o for o in w.scene.objects if o.movable and o.world_bounds()[0, 2] < 0.3)
    with pytest.raises(ActionError):
        w.pick(next(o.name for o in w.scene.objects if not o.movable))
    far = w.grid.sample(np.random.default_rng(5), 200)
    d = np.linalg.norm(far - obj.position[:2], axis=1)
    w.place_robot(*far[int(np.argmax(d))], 0.0)
    with pytest.raises(ActionError, match="away"):
        w.pick(obj.name)
    near = far[int(np.argmin(np.where(d > 0.3, d, np.inf)))]
    w.place_robot(*near, 0.0)
    r = AcousticRenderer(w.scene, RenderConfig(sample_rate=16000, block=512, occlusion=False,
                                               early_reflections=False, late_reverb=False))
    src = r.add_source(np.ones(16000, np.float32), attached_to=obj.name)
    r.add_listener((0, 0, 1))
    w.pick(obj.name)
    assert w.carried == obj.name
    for _ in range(10):
        w.drive([0.5, 0.3], 0.1)
    r.render_block()
    assert np.allclose(obj.position[:2], w.pose[:2])  # rides on the robot
    assert np.allclose(src.position[:2], w.pose[:2])  # and its sound with it
    for yaw in range(0, 360, 30):  # find a heading with room in front
        w.place_robot(*w.pose[:2], float(yaw))
        try:
            w.place()
            break
        except ActionError:
            continue
    assert w.carried is None
    assert obj.world_bounds()[0, 2] < 0.05  # on the floor
    assert w.free(*w.pose[:2])
    w.restore()
    assert w.carried is None


def test_depth_camera_measures_distance_and_clips():
    from sonicverse_core.sensors.camera import RGBDCamera

    scene = load_scene("shoebox:6x4x3")
    cam = RGBDCamera(scene, 64, 48, 90.0, 0.0, 10.0)
    try:
        img = cam.render(2.0, 2.0, 1.5, 0.0)  # facing the wall at x = 6: 4 m straight ahead
        assert img["rgb"].shape == (48, 64, 3) and img["rgb"].dtype == np.uint8
        c = img["depth"][24, 32]
        assert c == pytest.approx(4.0, abs=0.02)
        # depth is along the optical axis: the far wall reads 4 m wherever it is seen (|tan| < 0.5: columns 16-47)
        assert np.allclose(img["depth"][20:28, 18:46], 4.0, atol=0.02)
        # a side wall 2 m away, seen at tan = 0.75: forward depth 2 / 0.75
        assert img["depth"][24, 8] == pytest.approx(2.0 / ((32 - 8.5) / 32), abs=0.03)
    finally:
        cam.close()
    clip = RGBDCamera(scene, 64, 48, 90.0, 0.8, 3.5, rgb=False)
    try:
        d = clip.render(2.0, 2.0, 1.5, 0.0)["depth"]
        assert "rgb" not in clip.render(2.0, 2.0, 1.5, 0.0)
        assert np.all((d == 0) | ((d >= 0.8) & (d <= 3.5)))
        assert d[24, 32] == 0.0  # 4 m is beyond the sensor's range: invalid, like the real camera
    finally:
        clip.close()


def test_render_scene_merges_until_objects_move(home):
    from sonicverse_core.sensors.camera import RenderScene

    w = home
    w.restore()
    rs = RenderScene(w.scene)
    assert len(rs.nodes) == 0 and len(list(rs.scene.mesh_nodes)) == 1  # one primitive for the whole home
    door = w.scene.doors[0]
    w.set_door(door.name, 0.0)
    rs.sync()
    assert set(rs.nodes) == {door.name}
    assert np.allclose(rs.scene.get_pose(rs.nodes[door.name]), door.pose)
    w.set_door(door.name, 1.0)
