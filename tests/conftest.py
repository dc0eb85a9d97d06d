import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")


@pytest.fixture(scope="session")
def apartment():
    from sonicverse_core.scene.spec import load_scene

    return load_scene("builtin:apartment?seed=0")


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


def run_cli(*args, check_rc=None):
    """Run the real console command in a subprocess; returns CompletedProcess."""
    exe = shutil.which("sonicverse", path=str(Path(sys.executable).parent))
    cmd = [exe, *args] if exe else [sys.executable, "-m", "app.cli", *args]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=600)
    if check_rc is not None:
        assert r.returncode == check_rc, (r.returncode, r.stdout[-2000:], r.stderr[-2000:])
    return r


@pytest.fixture
def cli():
    """The real `sonicverse` command in a subprocess."""
    return run_cli
