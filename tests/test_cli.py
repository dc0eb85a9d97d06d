import json

import pytest


def test_scene_info_json(cli):
    r = cli("scene", "info", "builtin:apartment?seed=7", "--json", check_rc=0)
    info = json.loads(r.stdout)
    for key in ("rooms", "objects_per_category", "materials_m2", "floor_area_m2", "bounds", "triangles"):
        assert key in info
    assert 50 <= info["floor_area_m2"] <= 250
    assert info["materials_m2"]["ConcreteBlockPainted"] > 0


def test_scene_map_png(tmp_path, cli):
    out = tmp_path / "map.png"
    cli("scene", "map", "builtin:apartment?seed=11", "--out", str(out), check_rc=0)
    from PIL import Image

    img = Image.open(out)
    assert img.size[0] > 400 and img.size[1] > 300


@pytest.mark.parametrize("args", [
    ("scene", "info", "nowhere:else"),
    ("scene", "info", "/no/such/file.glb"),
    ("scene", "info", "shoebox:0x4x3"),
    ("scene", "info", "shoebox:4x4x3?material=Cheese"),
    ("scene", "map", "builtin:apartment", "--out", "/no/such/dir/map.png"),
])
def test_user_errors_are_one_line_exit_2(args, cli):
    r = cli(*args)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("sonicverse: error:"), r.stderr
    assert "Traceback" not in r.stderr


def test_help_for_every_subcommand(cli):
    for args in (("--help",), ("scene", "--help"), ("scene", "info", "--help"), ("scene", "map", "--help"),
                 ("bench", "--help"), ("bench", "rays", "--help"), ("demo", "--help")):
        r = cli(*args, check_rc=0)
        assert "usage:" in r.stdout


def test_bench_rays_reports_both_casters(cli):
    r = cli("bench", "rays", "--rays", "20000", check_rc=0)
    b = json.loads(r.stdout)
    assert b["embree_rays_per_s"] > 0 and b["numpy_rays_per_s"] > 0
    assert b["agreement"]["same_hit_fraction"] > 0.99
