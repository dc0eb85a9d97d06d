import subprocess
import sys

HEAVY = ("torch", "pyrender", "PyQt6", "openvr", "sounddevice", "OpenGL")


def test_core_imports_no_app_dependencies():
    code = ("import sys, sonicverse_core, sonicverse_core.scene, sonicverse_core.geometry, "
            "sonicverse_core.scene.apartment, sonicverse_core.scene.spec\n"
            "from sonicverse_core.scene.spec import load_scene; from sonicverse_core.geometry import NavGrid\n"
            "NavGrid(load_scene('builtin:apartment?seed=1'))\n"
            f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == ""


def test_core_imports_no_app_or_agents():
    r = subprocess.run([sys.executable, "-c", "import sys, sonicverse_core.scene.spec, sonicverse_core.geometry;"
                        "print([m for m in sys.modules if m.split('.')[0] in ('app', 'agents')])"],
                       capture_output=True, text=True)
    assert r.stdout.strip() == "[]", r.stdout + r.stderr


def test_the_cli_parser_builds_without_the_scene_model():
    """`sonicverse --help` and every argument error stay quick: building the parser reads the material tables but
    does not import trimesh (0.5-0.9 s here) or the other heavy parts."""
    code = ("import sys; from app.cli import build_parser; build_parser()\n"
            f"print(','.join(m for m in {HEAVY + ('trimesh', 'sonicverse_core.scene.model')!r} if m in sys.modules))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == ""
