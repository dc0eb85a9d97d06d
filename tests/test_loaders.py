"""Loaders over small fixtures written in each format by the tests themselves."""
import numpy as np
import pytest
import trimesh
from PIL import Image

from sonicverse_core.errors import MaterialError, MeshError, SceneFileError, SceneSpecError
from sonicverse_core.geometry.navgrid import NavGrid
from sonicverse_core.scene.model import StructureKind
from sonicverse_core.scene.shoebox import make_shoebox, shoebox_surfaces
from sonicverse_core.scene.spec import load_scene


def _room_meshes(L=5.0, W=4.0, H=2.8):
    surf = shoebox_surfaces(L, W, H)
    out = {}
    for name, corners in surf.items():
        m = trimesh.Trimesh(np.array(corners, float), [[0, 1, 2], [0, 2, 3]], process=False)
        cat = {"floor": "floor", "ceiling": "ceiling"}.get(name, "wall")
        out[f"{cat}_{name}"] = m
    chair = trimesh.creation.box(extents=(0.5, 0.5, 0.9))
    chair.apply_translation((2.5, 2.0, 0.455))
    out["chair.001"] = chair
    return out


def test_glb_with_material_names_and_categories(tmp_path):
    meshes = _room_meshes()
    meshes["floor_floor"].visual = trimesh.visual.TextureVisuals(material=trimesh.visual.material.PBRMaterial(name="Marble"))
    sc = trimesh.Scene()
    for name, m in meshes.items():
        sc.add_geometry(m, node_name=name, geom_name=name)
    f = tmp_path / "room.glb"
    sc.export(f)
    s = load_scene(str(f))
    mats = {p.name: p.material for p in s.static}
    assert mats["floor_floor"] == "Marble"  # visual material named after an acoustic material wins
    assert mats["wall_x0"] == "ConcreteBlockPainted"  # category 'wall' through the mapping
    assert {p.kind for p in s.static} == {StructureKind.WALL, StructureKind.FLOOR, StructureKind.CEILING}
    assert [o.category for o in s.objects] == ["chair"]  # not structure: a dynamic object
    g = NavGrid(s)
    assert not g.is_navigable([[2.5, 2.0]])[0] and g.is_navigable([[1.0, 1.0]])[0]


@pytest.mark.parametrize("suffix", [".obj", ".ply"])
def test_obj_and_ply(tmp_path, suffix):
    m = trimesh.util.concatenate(list(_room_meshes().values()))
    f = tmp_path / f"room{suffix}"
    m.export(f)
    s = load_scene(str(f))
    assert len(s.static_mesh()) == len(m.faces)
    np.testing.assert_allclose(s.bounds, [[0, 0, 0], [5, 4, 2.8]], atol=1e-6)


def _write_mp3d(d, nan=False):
    d.mkdir()
    meshes = _room_meshes()
    cats = {"wall": 1, "floor": 2, "ceiling": 3, "chair": 4}
    verts, faces, fcat = [], [], []
    off = 0
    for name, m in meshes.items():
        verts.append(m.vertices)
        faces.append(m.faces + off)
        fcat += [cats[name.split("_")[0].split(".")[0]]] * len(m.faces)
        off += len(m.vertices)
    v, f = np.concatenate(verts), np.concatenate(faces)
    if nan:
        v[0, 0] = np.nan
    lines = ["ply", "format ascii 1.0", f"element vertex {len(v)}", "property float x", "property float y",
             "property float z", f"element face {len(f)}", "property list uchar int vertex_indices",
             "property int face_material", "property int face_segment", "property int face_category", "end_header"]
    lines += [" ".join(f"{x:.6f}" for x in p) for p in v]
    lines += [f"3 {a} {b} {c} 0 0 {k}" for (a, b, c), k in zip(f, fcat)]
    (d / "house1.ply").write_text("\n".join(lines) + "\n")
    house = ["ASCII 1.1", "H house1 a 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0",
             "R 0 0 0 0 l 2.5 2 0 0 0 0 5 4 2.8 2.8 0 0 0 0",
             "C 1 1 wall 1 wall 0 0 0 0 0", "C 2 2 floor 2 floor 0 0 0 0 0", "C 3 3 ceiling 17 ceiling 0 0 0 0 0",
             "C 4 4 armchair 3 chair 0 0 0 0 0"]
    (d / "house1.house").write_text("\n".join(house) + "\n")


def test_mp3d_house(tmp_path):
    _write_mp3d(tmp_path / "h")
    s = load_scene(f"mp3d:{tmp_path / 'h'}")
    mats = {p.category: p.material for p in s.static}
    assert mats == {"wall": "ConcreteBlockPainted", "floor": "WoodPanel", "ceiling": "AcousticCeilingTiles",
                    "armchair": "PlywoodPanel"}
    assert [(r.type, round(r.area, 1)) for r in s.rooms] == [("living room", 20.0)]
    _write_mp3d(tmp_path / "bad", nan=True)
    with pytest.raises(MeshError, match="NaN"):
        load_scene(f"mp3d:{tmp_path / 'bad'}")


def test_igibson_scene(tmp_path):
    d = tmp_path / "Rs_int"
    (d / "urdf").mkdir(parents=True)
    (d / "shape").mkdir()
    (d / "layout").mkdir()
    meshes = _room_meshes()
    links, joints = [], []
    for name, m in meshes.items():
        cat = {"wall": "walls", "floor": "floors", "ceiling": "ceilings"}.get(name.split("_")[0], "chair")
        if cat == "chair":
            m = m.copy()
            m.apply_translation((-2.5, -2.0, 0.0))  # mesh in its own frame; placed by the joint
        m.export(d / "shape" / f"{name}.obj")
        links.append(f'<link name="{name}" category="{cat}"><visual><geometry><mesh filename="../shape/{name}.obj"/>'
                     f'</geometry></visual></link>')
        xyz = "2.5 2.0 0" if cat == "chair" else "0 0 0"
        joints.append(f'<joint name="j_{name}" type="fixed"><parent link="world"/><child link="{name}"/>'
                      f'<origin xyz="{xyz}" rpy="0 0 0"/></joint>')
    (d / "urdf" / "Rs_int_best.urdf").write_text(f'<robot name="Rs_int"><link name="world"/>{"".join(links)}'
                                                 f'{"".join(joints)}</robot>')
    trav = np.zeros((1200, 1200), np.uint8)  # 12 m at 1 cm, origin at the centre
    trav[600:600 + 400, 600:600 + 250] = 255  # x 0..2.5, y 0..4: only the left half is traversable
    Image.fromarray(trav).save(d / "layout" / "floor_trav_0.png")
    s = load_scene(f"igibson:{d}")
    assert {p.material for p in s.static if p.kind == StructureKind.WALL} == {"ConcreteBlockPainted"}
    assert {p.material for p in s.static if p.kind == StructureKind.FLOOR} == {"WoodPanel"}
    chair = s.objects[0]
    np.testing.assert_allclose(chair.world_bounds().mean(0)[:2], [2.5, 2.0], atol=1e-6)
    g = NavGrid(s)
    assert g.is_navigable([[1.2, 2.0]])[0] and not g.is_navigable([[4.0, 2.0]])[0]


def test_bad_inputs(tmp_path):
    with pytest.raises(SceneSpecError):
        load_scene("builtin:castle")
    with pytest.raises(SceneSpecError):
        load_scene("shoebox:6x4")
    with pytest.raises(MeshError, match="zero volume"):
        load_scene("shoebox:6x0x3")
    with pytest.raises(MaterialError):
        load_scene("shoebox:6x4x3?material=Chocolate")
    with pytest.raises(SceneFileError):
        load_scene(str(tmp_path / "missing.glb"))
    with pytest.raises(SceneFileError):
        load_scene(f"mp3d:{tmp_path}")
    with pytest.raises(SceneSpecError):
        load_scene("builtin:apartment?seed=x")
    with pytest.raises(SceneSpecError):
        load_scene("builtin:apartment?sede=1")
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    with pytest.raises((MeshError, SceneFileError)):
        load_scene(str(empty))
    nan = tmp_path / "nan.obj"
    nan.write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(MeshError, match="NaN"):
        load_scene(str(nan))
    assert make_shoebox(1, 1, 1).rooms[0].volume == pytest.approx(1.0)
