"""The semantic camera (category and instance ids per pixel) agrees with the scene: each pixel's id is the first
surface an Embree ray through that pixel hits; ids are stable across homes; actors (the person) are labelled; the
env serves it as a sensor."""
import numpy as np
import pytest

from sonicverse_core.geometry.navgrid import NavGrid
from sonicverse_core.geometry.raycast import SceneRayCaster
from sonicverse_core.scene.spec import load_scene
from sonicverse_core.sensors.camera import CLASSES, RGBDCamera, camera_matrix, decode_ids, id_colour, part_category

W, H, HFOV = 96, 72, 90.0


def _rays(x, y, z, yaw, pitch):
    """A ray through every pixel centre of the camera (row-major), world frame."""
    pose = camera_matrix(x, y, z, yaw, pitch)
    tx = np.tan(np.radians(HFOV) / 2)
    ty = tx * H / W
    c, r = np.meshgrid(np.arange(W), np.arange(H))
    u = ((c + 0.5) / W * 2 - 1) * tx
    v = (1 - (r + 0.5) / H * 2) * ty
    d_cam = np.stack([u, v, -np.ones_like(u)], -1).reshape(-1, 3)
    d = d_cam @ pose[:3, :3].T
    return np.tile(pose[:3, 3], (len(d), 1)), d / np.linalg.norm(d, axis=1, keepdims=True)


def _instances_by_rays(scene, rc, origins, dirs):
    hits = rc.first_hit(origins, dirs)
    n_obj, off = len(scene.objects), rc.part_offset()
    names = {o.name: i + 1 for i, o in enumerate(scene.objects)}
    out = np.zeros(len(dirs), np.int64)
    for k in np.flatnonzero(hits.hit):
        p = int(hits.part[k])
        out[k] = n_obj + 1 + p if p < off else names[rc.part_name(p)]
    return out.reshape(H, W)


@pytest.mark.parametrize("seed", [0, 3, 7])
def test_semantic_pixels_are_what_a_ray_hits(seed):
    """Per pixel, the category of the first surface an Embree ray through the pixel centre hits. Where they differ
    the two surfaces lie at the same depth (seams of coplanar parts: a wall and its window, a wall's foot and the
    floor) or the pixel is on a silhouette: at most 0.5% of pixels disagree on a surface at another depth."""
    scene = load_scene(f"builtin:apartment?seed={seed}")
    grid = NavGrid(scene)
    rc = SceneRayCaster(scene)
    cam = RGBDCamera(scene, W, H, HFOV, rgb=False, depth=True, semantic=True)
    rng = np.random.default_rng(seed)
    agree, other_depth, total, seen = 0, 0, 0, set()
    try:
        for p in grid.sample(rng, 6):
            yaw, pitch = float(rng.uniform(-180, 180)), float(rng.uniform(-20, 10))
            out = cam.render(p[0], p[1], 1.2, yaw, pitch)
            origins, dirs = _rays(p[0], p[1], 1.2, yaw, pitch)
            ref = cam.labels.lut[_instances_by_rays(scene, rc, origins, dirs)]
            fwd = -camera_matrix(p[0], p[1], 1.2, yaw, pitch)[:3, 2]
            z_ray = (rc.first_hit(origins, dirs).distance * (dirs @ fwd)).reshape(H, W)
            bad = out["semantic"] != ref
            agree += int(np.sum(~bad))
            other_depth += int(np.sum(bad & (np.abs(out["depth"] - z_ray) > 0.05 * z_ray)))
            total += ref.size
            assert np.array_equal(out["semantic"], cam.labels.lut[out["instance"]])
            assert np.all(out["instance"][out["depth"] > 0] > 0)  # every surface seen has an id
            seen |= set(np.unique(out["semantic"]).tolist())
    finally:
        cam.close()
    assert agree / total >= 0.97, agree / total
    assert other_depth / total <= 0.005, other_depth / total
    # ids mean the same in every home: the fixed classes first
    assert cam.labels.categories[: len(CLASSES)] == list(CLASSES)
    assert CLASSES.index("wall") in seen and CLASSES.index("floor") in seen


def test_ids_round_trip_and_part_names():
    ids = np.array([0, 1, 255, 256, 70_000, 2**24 - 1])
    assert np.array_equal(decode_ids(id_colour(ids)[None, :, :3])[0], ids)
    assert [part_category(n) for n in ("wall_2_1", "Window.003", "floor bathroom", "x0", "coffee_table_2", "")] == \
        ["wall", "window", "floor", "wall", "coffee_table", "structure"]


def test_actors_and_moved_objects_are_labelled():
    from sonicverse_core.world.person import body_mesh

    scene = load_scene("shoebox:6x5x3")
    cam = RGBDCamera(scene, W, H, HFOV, rgb=True, depth=False, semantic=True)
    cam.set_actor("person", body_mesh(1.75, 0.25))
    pose = np.eye(4)
    pose[:3, 3] = (4.0, 2.5, 0.0)
    cam.move_actor("person", pose)
    out = cam.render(1.0, 2.5, 1.2, 0.0, 0.0)
    person = CLASSES.index("person")
    rows, cols = np.nonzero(out["semantic"] == person)
    assert len(cols) > 60 and abs(cols.mean() - (W - 1) / 2) < 3  # straight ahead, 3 m away (0.45 m wide: 7 columns)
    assert rows.max() - rows.min() > 20  # from head to feet: 1.75 m at 3 m is 28 rows here
    assert "rgb" in out and "depth" not in out
    cam.clear_actors()
    assert np.sum(cam.render(1.0, 2.5, 1.2, 0.0, 0.0)["semantic"] == person) == 0
    cam.close()


def test_env_serves_semantic_observations():
    from sonicverse_core.tasks import make_env

    env = make_env("AudioGoal", split="test", sensors=("semantic", "depth", "pose"), width=64, height=48)
    obs, _ = env.reset(seed=1)
    assert env.observation_space["semantic"].contains(obs["semantic"])
    assert obs["semantic"].shape == (48, 64, 1) and obs["semantic"].max() > 0
    wall = CLASSES.index("wall")
    assert np.any(obs["semantic"] == wall) or np.any(obs["semantic"] == CLASSES.index("floor"))
    env.close()


def test_bench_camera_reports_every_output(cli):
    import json

    r = cli("bench", "camera", "--frames", "10", "--size", "32")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    assert set(d["ms_per_frame"]) == {"depth", "rgbd", "rgbd_flat_look", "rgbd_msaa", "rgbd_pbr_shadows", "semantic",
                                      "rgbd+semantic"}
    assert d["look_bake_s"] > 0
    assert d["ratio_to_depth"]["depth"] == 1.0 and all(v > 0 for v in d["ms_per_frame"].values())
