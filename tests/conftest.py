import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.audio_rt.jack import JackServer as _JackServer
from sonicverse_core.errors import SonicverseError

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")


@pytest.fixture(scope="session")
def apartment():
    from sonicverse_core.scene.spec import load_scene

    return load_scene("builtin:apartment?seed=0")


@pytest.fixture(scope="session")
def audiogoal_random_test9():
    """`random` on the first 9 AudioGoal test episodes of seed 0, once per session: the shipped AudioGoal policies'
    checks play some of them and compare against it (an evaluation's episode i depends on the seed and i alone, so
    `first=6` plays the same episode 6; tests/test_learned.py checks that)."""
    from app.tasks.evaluate import run_eval

    return run_eval("AudioGoal", "random", 9, split="test", seed=0)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def wrapped_stop():
    """Fires a SIGTERM's raise (errors.stop; or ``raise_()`` when given, Ctrl-C's say) the way Python 3.11 hands it
    on when it lands while a class body binds its fields (a task module being imported): inside a RuntimeError. The
    noted stop is cleared afterwards."""
    from sonicverse_core import errors

    def fire(raise_=lambda: errors.stop("terminated (SIGTERM)")):
        class Field:
            def __set_name__(self, owner, name):
                raise_()

        type("Episode", (), {"extra": Field()})

    yield fire
    errors._STOPPED.clear()


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


class JackServer(_JackServer):
    """app.audio_rt.jack.JackServer, whose start-up failures fail the test (never a skip: the README's set-up
    installs jackd2)."""

    def __init__(self, *a, **kw):
        try:
            super().__init__(*a, **kw)
        except SonicverseError as exc:
            pytest.fail(str(exc))

    def start(self) -> None:
        try:
            super().start()
        except SonicverseError as exc:
            pytest.fail(str(exc))


def _leave_jack(sd, timeout: float = 30.0) -> None:
    """PortAudio of this process leaves the JACK server before the server stops (its exit would assert on a dead
    one). Pa_Terminate closes PortAudio's JACK client, and jack2's jack_client_close can deadlock on a mutex its
    notification thread left taken (jackaudio/jack2 issue 395, seen here once as a test run that never ended): so it
    runs in a thread of its own, and where it has not returned in ``timeout`` seconds PortAudio is marked terminated
    (its exit handler then leaves it alone), the hung thread is abandoned and the run goes on, saying so."""
    import threading

    if sd is None or not sd._initialized:
        return
    done = threading.Thread(target=sd._terminate, name="pa-terminate", daemon=True)
    done.start()
    done.join(timeout)
    if done.is_alive():
        sd._initialized = 0
        print(f"\nconftest: PortAudio's Pa_Terminate did not return in {timeout:g} s (jack_client_close hung); "
              f"abandoned it and stopped the JACK server", file=sys.stderr)


@pytest.fixture(scope="session")
def jack():
    """The session's JACK server; its name goes to JACK_DEFAULT_SERVER so that PortAudio (in this process, in
    audio workers and in CLI subprocesses) uses it."""
    srv = JackServer(f"sv-test-{os.getpid()}")
    old = os.environ.get("JACK_DEFAULT_SERVER")
    os.environ["JACK_DEFAULT_SERVER"] = srv.name
    yield srv
    _leave_jack(sys.modules.get("sounddevice"))
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


@pytest.fixture
def policy_batch():
    """``policy_batch(T, B, cfg)``: seeded random depth, spectrogram and pose inputs for a policy of ``cfg``,
    shaped (T, B, ...)."""
    import torch

    def make(T, B, cfg):
        g = torch.Generator().manual_seed(0)
        return (torch.rand(T, B, *cfg.depth_hw, 1, generator=g) * 10,
                torch.rand(T, B, *cfg.spec_shape, generator=g) * 5, torch.rand(T, B, cfg.pose_dim, generator=g))

    return make
