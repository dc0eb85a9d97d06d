"""JACK and PortAudio around the pipeline: the JACK servers we start (they die with their user, sweep what killed
sessions left, and the test run's PortAudio teardown cannot hang it), and streams that run their DSP in this process
(``mode="thread"``): several engines in one process, and the BLAS their callbacks call."""


def _engine():
    """A thread-mode engine in a shoebox: one source, one robot, the loopback's test signal, no microphone."""
    from app.audio_rt.config import AudioConfig, AudioScene, SourceSpec
    from app.audio_rt.engine import AudioEngine

    return AudioEngine(AudioConfig(mode="thread", mic=False, test_signal=True),
                       AudioScene("shoebox:6x5x3", sources=[SourceSpec("sofa/0", (4.0, 3.0, 1.2), 0.1)],
                                  robots=[(1.5, 1.0, 0.4, 0.0)], head=(2.0, 2.5, 1.6, 0.0, 0.0)))


# --- streams in this process --------------------------------------------------------------------------------------
def test_a_second_engine_in_the_same_process_leaves_the_first_ones_stream_running(jack):
    """``mode="thread"`` runs the stream in this process. Naming the JACK client re-initialised PortAudio at every
    start, which closed the streams the process had open: the first engine's stopped calling back for good, its
    state still 'running', and nothing reported (session 67)."""
    from threadpoolctl import threadpool_info

    import scipy.linalg  # noqa: F401 - both OpenBLAS libraries loaded before

    def blas_threads():
        return {lib["filepath"]: lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}

    before = blas_threads()
    a, b = _engine(), _engine()
    try:
        ia = a.start()
        assert a.wait_callbacks(20) >= 20
        ib = b.start()
        assert ib["jack_client"] == ia["jack_client"]  # one PortAudio, one client, two streams on it
        assert b.wait_callbacks(20) >= 20
        assert a.wait_callbacks(20, timeout=5.0) >= 20, (a.poll(), a.telemetry())
        # while a stream runs its DSP in this process, its BLAS runs one thread (the next test says why)
        a.stop()
        assert set(blas_threads().values()) == {1}  # b still runs: a's stop leaves the limit in place
    finally:
        b.stop()
        a.stop()
    assert blas_threads() == before  # restored once no stream of this process runs


_DOORS_UNDER_A_THREAD_STREAM = """
import gc
from app.audio_rt.config import AudioConfig, AudioScene
from app.audio_rt.engine import AudioEngine
from app.audio_rt.loopback import random_sources
from sonicverse_core.acoustics import coupling

srcs, head = random_sources("builtin:apartment", 2, 0)
eng = AudioEngine(AudioConfig(mode="thread", mic=False), AudioScene("builtin:apartment", sources=srcs, head=head))
eng.start()
assert eng.wait_callbacks(10) >= 10
made = coupling._SPLITS[0]
for ajar in (0.5, 0.25):  # every door half open, then a quarter: states the warm-up did not make (it moves them
    eng.set_poses(head, doors=[ajar] * len(eng.scene.doors))  # open and shut), so the callback makes them
    assert eng.wait_callbacks(20) >= 20, eng.poll()
eng.stop()
print(coupling._SPLITS[0] - made, eng.events, gc.collect() >= 0)
"""


def test_doors_moving_under_a_stream_in_this_process_leave_the_interpreter_intact(jack):
    """``mode="thread"``: a door that moves makes the coupled rooms' decay again in the audio server's thread
    (``np.linalg.inv`` and ``eigh``). Multithreaded OpenBLAS overran that thread's small stack there and wrote over
    the interpreter's memory: the next garbage collection crashed (SIGSEGV, session 67). The engine runs the
    process's BLAS on one thread while such a stream runs."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", _DOORS_UNDER_A_THREAD_STREAM], cwd=root, capture_output=True,
                         text=True, timeout=300, env={**os.environ, "PYTHONPATH": str(root)})
    assert out.returncode == 0, (out.returncode, out.stderr[-1500:])
    assert out.stdout.split() == ["2", "[]", "True"], out.stdout  # both door changes made it again, no error


# --- the servers we start -------------------------------------------------------------------------------------
def test_a_jack_server_does_not_outlive_a_killed_user(tmp_path):
    """A test run or a benchmark killed with SIGKILL cannot stop its JACK server: the server gets SIGTERM with it
    (setpriv --pdeathsig), so no real-time server is left running."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from conftest import ROOT

    code = ("import os, sys, time\nfrom app.audio_rt.jack import JackServer\n"
            "s = JackServer(f'sv-orphan-{os.getpid()}')\nprint(s.proc.pid, flush=True)\ntime.sleep(600)\n")
    user = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    pid = int(user.stdout.readline())
    os.kill(pid, 0)  # running
    user.send_signal(signal.SIGKILL)
    user.wait(timeout=30)
    deadline = time.monotonic() + 30
    while True:  # polled: it is a child of init now, reaped there
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            break
        assert time.monotonic() < deadline, f"jackd {pid} outlived the process that started it"
        time.sleep(0.05)


def test_a_killed_sessions_jack_leftovers_are_swept_when_the_next_server_starts(private_jack):
    """A session killed with SIGKILL while its stream ran leaves its server's client futex files in /dev/shm (its
    server, stopped by pdeathsig under the client, cannot remove them; seen with ``bench vr``). The next server we
    start removes those of servers whose owner is gone, and no one else's."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid, uid = int(dead.stdout), os.getuid()
    shm = Path("/dev/shm")
    left = shm / f"jack_sem.{uid}_sv-bench-{dead_pid}_sonicverse-1"
    left_k = shm / f"jack_sem.{uid}_sv-priv-{dead_pid}-3_sonicverse-2"
    alive = shm / f"jack_sem.{uid}_sv-bench-{os.getpid()}_sonicverse-3"  # a live session's: in use
    other = shm / f"jack_sem.{uid}_studio_ardour-{dead_pid}"  # not our naming: someone else's server
    for p in (left, left_k, alive, other):
        p.write_bytes(bytes(12))
    try:
        private_jack()
        assert not left.exists() and not left_k.exists()
        assert alive.exists() and other.exists()
    finally:
        for p in (left, left_k, alive, other):
            p.unlink(missing_ok=True)


def test_a_hung_portaudio_terminate_does_not_hang_the_test_run(capsys):
    """The session fixture's PortAudio teardown (``conftest._leave_jack``): jack2's jack_client_close can deadlock
    (jackaudio/jack2 issue 395), so Pa_Terminate runs in a thread of its own; one that has not returned by the
    timeout is abandoned, PortAudio is marked terminated (its exit handler leaves it alone) and a line says so. One
    that returns is simply done."""
    import threading

    from conftest import _leave_jack

    release = threading.Event()

    class PortAudio:  # sounddevice's module state as _leave_jack reads and writes it
        _initialized = 1

        def __init__(self, hangs):
            self.hangs = hangs

        def _terminate(self):
            if self.hangs:
                release.wait()
            else:
                self._initialized -= 1

    hung = PortAudio(hangs=True)
    try:
        _leave_jack(hung, timeout=0.2)
    finally:
        release.set()
    assert hung._initialized == 0 and "did not return in 0.2 s" in capsys.readouterr().err
    fine = PortAudio(hangs=False)
    _leave_jack(fine, timeout=5.0)
    assert fine._initialized == 0 and capsys.readouterr().err == ""
    _leave_jack(None)  # sounddevice never imported: nothing to do
