"""Furniture built from parts: every category for many seeds, parts inside the object's proxy box (so free of the
walls the layout kept it from), each part with a known material and colour; the acoustic engine's geometry is the
parts (with their materials), the navigation's the proxies; the category mapping still decides the main material;
the same seed gives the same furniture."""
from collections import Counter

import numpy as np
import pytest

from sonicverse_core.scene import furniture
from sonicverse_core.scene.materials import MATERIAL_INDEX
from sonicverse_core.scene.spec import load_scene

TOL = 0.005  # m: handles stand 4 mm proud of a door leaf


def _homes(n=24):
    return [load_scene(f"builtin:apartment?seed={s}") for s in range(n)]


def test_every_category_builds_inside_its_proxy_with_known_materials():
    seen = Counter()
    for scene in _homes():
        for o in scene.objects:
            assert o.parts, o.name  # every object of a home is built from parts
            lo, hi = o.mesh.bounds
            for p in o.parts:
                assert p.material is None or p.material in MATERIAL_INDEX, (o.name, p.name, p.material)
                assert len(p.colour) == 4 and all(0 <= c <= 255 for c in p.colour)
                v = p.mesh.vertices
                assert np.all(v >= lo - TOL) and np.all(v <= hi + TOL), (o.name, p.name, v.min(0), v.max(0), lo, hi)
                assert p.mesh.is_volume or len(p.mesh.faces) >= 12, (o.name, p.name)
            seen[o.category] += 1
    assert set(furniture.BUILDERS) <= set(seen), set(furniture.BUILDERS) - set(seen)
    assert seen["door"] > 0


@pytest.mark.parametrize("category, must", [
    ("sofa", {"seat cushion": "CurtainHeavy", "back cushion": "CurtainHeavy", "leg": "WoodPanel"}),
    ("bed", {"mattress": "CurtainHeavy", "pillow": "CurtainHeavy", "headboard": "WoodPanel"}),
    ("breakfast_table", {"top": "WoodPanel"}),
    ("standing_tv", {"screen": "GlassThin"}),
    ("toilet", {"bowl": "PolishedConcreteOrTile", "tank": "PolishedConcreteOrTile"}),
    ("shelf", {"board": "WoodPanel", "side": "WoodPanel"}),
    ("straight_chair", {"seat": "WoodPanel"}),
    ("picture", {"frame": "WoodPanel"}),
])
def test_parts_have_their_semantics_and_materials(category, must):
    rng = np.random.default_rng(0)
    for _ in range(10):
        parts = furniture.build(category, 1.0, 0.8, 0.9, rng)
        mats = {}
        for p in parts:
            mats.setdefault(p.name, p.material)
        for name, mat in must.items():
            assert name in mats and mats[name] == mat, (category, name, mats)
    chair = furniture.build("straight_chair", 0.45, 0.45, 0.9, np.random.default_rng(1))
    assert sum(p.name == "leg" for p in chair) == 4


def test_the_ear_hears_the_parts_and_the_robot_drives_the_proxies():
    scene = load_scene("builtin:apartment?seed=0")
    heard, proxies = scene.dynamic_mesh(), scene.dynamic_mesh(proxies=True)
    assert len(heard.faces) > 5 * len(proxies.faces)
    assert len(proxies.faces) == 12 * len(scene.objects)  # one box each
    sofa = next(o for o in scene.objects if o.category == "sofa")
    faces = [i for i, n in enumerate(heard.part_names) if n == sofa.name]
    mats = {k for k, v in MATERIAL_INDEX.items() if v in set(heard.face_material[np.isin(heard.face_part, faces)])}
    assert {"CurtainHeavy", "WoodPanel"} <= mats  # fabric and wooden legs, not one material for the whole sofa


def test_the_mapping_still_decides_the_main_material():
    from sonicverse_core.scene.apartment import generate_apartment
    from sonicverse_core.scene.mapping import MAPPINGS

    m = MAPPINGS["builtin"].updated({"sofa": "Marble"}, name="test")
    scene = generate_apartment(0, m)
    sofa = next(o for o in scene.objects if o.category == "sofa")
    looks = {name: mat for name, mat, _, _ in sofa.looks()}
    assert looks["base"] == "Marble" and looks["seat cushion"] == "CurtainHeavy"


def test_same_seed_same_furniture():
    a, b = load_scene("builtin:apartment?seed=3"), load_scene("builtin:apartment?seed=3")
    for oa, ob in zip(a.objects, b.objects):
        assert [p.colour for p in oa.parts] == [p.colour for p in ob.parts]
        assert all(np.array_equal(p.mesh.vertices, q.mesh.vertices) for p, q in zip(oa.parts, ob.parts))
    styles = {len(o.parts) for s in _homes(12) for o in s.objects if o.category == "straight_chair"}
    assert len(styles) > 1  # chairs come in more than one style


def test_gallery_shows_every_room_type_and_category(tmp_path, cli):
    import json

    r = cli("scene", "gallery", "builtin:apartment", "builtin:apartment?seed=1", "--out", str(tmp_path / "g.png"),
            "--json")
    assert r.returncode == 0, r.stderr
    d = json.loads(r.stdout)
    scenes = [load_scene("builtin:apartment"), load_scene("builtin:apartment?seed=1")]
    assert set(d["rooms"]) == {room.type for s in scenes for room in s.rooms}
    assert set(d["categories"]) == {o.category for s in scenes for o in s.objects}
    assert (tmp_path / "g.png").stat().st_size > 50_000


def test_bodies_are_built_from_parts():
    """The TurtleBot 2 and the person of the VR views: parts where the robot's config puts them."""
    import trimesh

    from sonicverse_core.world.robot import RobotConfig

    c = RobotConfig()
    bot = furniture.turtlebot(c)
    names = [p.name for p in bot]
    assert names.count("plate") == 3 and names.count("microphone") == 2 and "camera" in names
    mics = [p.mesh.centroid for p in bot if p.name == "microphone"]
    assert np.allclose([m[2] for m in mics], c.ear_height, atol=1e-6)
    assert abs(abs(mics[0][1] - mics[1][1]) - c.ear_spacing) < 1e-6
    cam = next(p for p in bot if p.name == "camera").mesh.centroid
    assert abs(cam[2] - c.camera_height) < 1e-6
    m = trimesh.util.concatenate([p.mesh for p in bot])
    assert np.hypot(*m.vertices[:, :2].T).max() <= c.radius + 0.01
    body = furniture.person(1.8, 0.25)
    mb = trimesh.util.concatenate([p.mesh for p in body])
    assert abs(mb.bounds[1, 2] - 1.8) < 1e-6 and mb.bounds[0, 2] == 0.0
    assert np.hypot(*mb.vertices[:, :2].T).max() <= 0.27
    assert {"head", "torso", "arm", "hand", "leg", "shoe"} <= {p.name for p in body}


def test_scene_info_reports_the_look():
    """`scene info`'s visual size is what pyrender uploads (checked on a primitive of the same kind), and the
    material areas count the parts the ear hears."""
    import pyrender
    import trimesh

    from sonicverse_core.scene.summary import VERTEX_BYTES, scene_info

    box = trimesh.creation.box()
    box.visual.face_colors = np.tile([10, 20, 30, 255], (12, 1)).astype(np.uint8)
    prim = pyrender.Mesh.from_trimesh(box, smooth=False).primitives[0]
    assert prim.positions.nbytes + prim.normals.nbytes + prim.color_0.nbytes == VERTEX_BYTES * 3 * 12
    scene = load_scene("builtin:apartment")
    info = scene_info(scene)
    assert info["visual"]["triangles"] == scene.triangle_count == len(scene.static_mesh()) + len(scene.dynamic_mesh())
    assert info["visual"]["object_parts"] == sum(len(o.parts) for o in scene.objects)
    assert info["materials_m2"]["CurtainHeavy"] > 0 and info["materials_m2"]["Metal"] > 0  # cushions, handles
