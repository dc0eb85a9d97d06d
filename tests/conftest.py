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


class JackServer:
    """A JACK server with the dummy backend (a real clocked audio device), started and killed by PID."""

    def __init__(self, name: str, rate: int = 48000, period: int = 256, playback: int = 2, capture: int = 2):
        self.name = name
        exe = shutil.which("jackd")
        if exe is None:  # never a skip: the README's set-up installs jackd2
            pytest.fail("jackd not found: install the Debian package jackd2 (scripts/install-system.sh)")
        self.cmd = [exe, "-n", name, "-d", "dummy", "-r", str(rate), "-p", str(period), "-P", str(playback),
                    "-C", str(capture)]
        self.proc = None
        self.start()

    def start(self) -> None:
        self.proc = subprocess.Popen(self.cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        w = subprocess.run(["jack_wait", "-s", self.name, "-w", "-t", "20"], capture_output=True, text=True)
        if w.returncode != 0 or self.proc.poll() is not None:
            err = self.proc.stderr.read() if self.proc.poll() is not None else w.stdout
            self.stop()
            pytest.fail(f"JACK server '{self.name}' did not start: {err[-500:]}")

    def stop(self) -> None:
        """SIGTERM (a clean shutdown that leaves no stale entry in JACK's server registry), SIGKILL if it hangs."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        self.proc = None


@pytest.fixture(scope="session")
def jack():
    """The session's JACK server; its name goes to JACK_DEFAULT_SERVER so that PortAudio (in this process, in
    audio workers and in CLI subprocesses) uses it."""
    srv = JackServer(f"sv-test-{os.getpid()}")
    old = os.environ.get("JACK_DEFAULT_SERVER")
    os.environ["JACK_DEFAULT_SERVER"] = srv.name
    yield srv
    srv.stop()
    if old is None:
        os.environ.pop("JACK_DEFAULT_SERVER", None)
    else:
        os.environ["JACK_DEFAULT_SERVER"] = old


@pytest.fixture
def private_jack(monkeypatch, request):
    """A JACK server of this test's own (to stop mid-stream, or with other channel counts)."""
    servers = []

    def make(**kw):
        srv = JackServer(f"sv-priv-{os.getpid()}-{len(servers)}", **kw)
        servers.append(srv)
        monkeypatch.setenv("JACK_DEFAULT_SERVER", srv.name)
        return srv

    yield make
    for s in servers:
        s.stop()
