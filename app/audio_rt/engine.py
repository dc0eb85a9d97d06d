"""The main side of the real-time audio pipeline: start, feed poses, read what listeners heard, watch health.

    with AudioEngine(AudioConfig(device="system"), AudioScene("builtin:apartment", robots=[(2, 1, 0.4, 0)])) as eng:
        while running:                       # the frame loop
            eng.set_poses(t, head=(x, y, z, yaw, pitch), robots=[...])
            robot_ears = eng.read_ears(1)    # (2, n) float32: what the robot heard since the last call
            for event in eng.poll():         # callback errors, device loss: reported here, never raised by audio
                log(event)
"""
from __future__ import annotations

import dataclasses
import multiprocessing as mp
import os
import socket
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection

import numpy as np

from app.audio_rt import config as C
from app.audio_rt.config import AudioConfig, AudioScene
from app.audio_rt.core import Shared, shared_layout
from app.audio_rt.heap import ENV as HEAP_ENV, keep_heap
from app.audio_rt.poses import PoseLayout
from app.audio_rt.shared import SharedBlock
from sonicverse_core import errors as E


# the worker's math libraries run on the callback thread only: no BLAS/OpenMP pools spinning beside it
_SINGLE_THREADED = {k: "1" for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
                                     "NUMBA_NUM_THREADS")}


class _OneBlasThread:
    """Thread mode's counterpart of :data:`_SINGLE_THREADED`: the process's BLAS libraries run one thread while any
    stream of this process runs its DSP in the audio server's thread (threadpoolctl; the limit held by a count, so
    that the first of two engines to stop does not lift it under the second). Multithreaded OpenBLAS's LAPACK
    (``np.linalg.inv``, ``eigh``: the coupled rooms' decay, made again in the callback when a door moves) overran
    the small stack of a JACK client's thread and wrote over the interpreter's memory: the process crashed later
    (SIGSEGV in the garbage collector; measured, session 67). With one thread it stays within it."""

    _lock = threading.Lock()
    _held = 0
    _limits = None

    @classmethod
    def hold(cls) -> None:
        threadpool_limits = E.require("threadpoolctl", "audio mode 'thread'").threadpool_limits
        import scipy.linalg  # noqa: F401 - SciPy's own OpenBLAS, loaded now so that the limit covers it too

        with cls._lock:
            if cls._held == 0:
                cls._limits = threadpool_limits(limits=1, user_api="blas")
            cls._held += 1

    @classmethod
    def release(cls) -> None:
        with cls._lock:
            if cls._held == 0:
                return
            cls._held -= 1
            if cls._held == 0:
                cls._limits.restore_original_limits()
                cls._limits = None


class AudioEngine:
    def __init__(self, cfg: AudioConfig = AudioConfig(), scene: AudioScene = AudioScene()):
        if scene.spec is not None and not scene.doors:
            from sonicverse_core.scene.spec import load_scene

            doors = load_scene(scene.spec).doors
            scene = dataclasses.replace(scene, doors=tuple(d.name for d in doors),
                                        door_open=tuple(d.open_fraction for d in doors))
        self.cfg, self.scene = cfg, scene
        self.pose_layout = PoseLayout(len(scene.robots), len(scene.sources), len(scene.doors))
        self.n_listeners = 1 + len(scene.robots)
        self.layout = shared_layout(cfg, self.n_listeners, self.pose_layout)
        self.info: dict | None = None
        self.state = "stopped"
        self.events: list[str] = []
        self._proc = self._thread = self._conn = self._block = self._rproc = self._rconn = None
        self._blas = False
        self._errors_seen = 0
        self._t0 = time.monotonic()
        self._door_values = np.array(scene.door_open if scene.door_open else [1.0] * len(scene.doors), float)
        self.opens = 0

    # --- life cycle ---------------------------------------------------------------------------------------------
    def start(self) -> dict:
        """Open the stream (a new worker); raises DeviceError / ConfigError with a one-line message on failure."""
        if self.state == "running":
            return self.info
        cfg = self.cfg
        thread = cfg.mode == "thread"
        from app.audio_rt.sched import nice_roles

        nice_roles()  # a bad SONICVERSE_RT_NICE is a ConfigError here, not an error in every callback there
        keep_heap()  # this process runs the frame loop: its freed memory must not stall the audio (heap.py)
        self._block = SharedBlock(self.layout.size, private=thread)
        self.sh = Shared(self.layout, self._block.buf, self.n_listeners)
        self._errors_seen = 0
        rmsg = msg = None
        try:
            if thread:
                _OneBlasThread.hold()  # before the stream's thread can call LAPACK (released by _kill)
                self._blas = True
                parent, child = mp.Pipe()
                from app.audio_rt.worker import run

                self._thread = threading.Thread(target=run, name="sonicverse-audio", daemon=True,
                                                args=(child, cfg, self.scene, None, self._block.buf))
                self._thread.start()
                self._conn = parent
                msg = self._wait(cfg.start_timeout)
            else:
                # the robots render in a process of their own, the callback's renders the user's ears only
                # (worker.py); with robots, the stream's worker first checks the devices (a wrong one fails at once,
                # not after the robots' warm-up), then waits while the robots' worker warms up: ready before the
                # stream starts, the robots render from its first block (and two workers never compile at once)
                role = "user" if self.scene.robots else "all"
                self._proc, self._conn = self._spawn((cfg, self.scene, self._block.path, role))
                msg = self._wait(cfg.start_timeout)
                if role == "user" and msg is not None and msg[0] == "checked":
                    self._rproc, self._rconn = self._spawn((cfg, self.scene, self._block.path, "robots"))
                    rmsg = self._wait(cfg.start_timeout, self._rconn, self._rproc)
                    msg = None
                    if rmsg is not None and rmsg[0] == "ready":
                        self._conn.send(("go",))
                        msg = self._wait(cfg.start_timeout)
        finally:
            self._block.release()  # the workers have it mapped (it never had a name: nothing to leave behind)
        if self._rconn is not None and (rmsg is None or rmsg[0] != "ready"):
            self._kill()
            self.state = "failed"
            if rmsg is None:
                raise E.DeviceError("the robot listeners' audio process did not start")
            raise getattr(E, rmsg[1], E.DeviceError)(rmsg[2])
        if msg is None:
            self._kill()
            raise E.DeviceError(f"the audio worker did not start within {cfg.start_timeout:.0f} s")
        if msg[0] == "error":
            self._kill()
            self.state = "failed"
            raise getattr(E, msg[1], E.DeviceError)(msg[2])
        msg[1]["robot_listeners"] = "own process" if self._rconn is not None else "in the callback"
        self.info, self.state = msg[1], "running"
        self._mark = None
        self.opens += 1
        self.sh.mic.skip_to_end()
        for r in self.sh.ears:
            r.skip_to_end()
        return self.info

    def _spawn(self, payload) -> tuple[subprocess.Popen, Connection]:
        """A worker in a fresh interpreter (not fork: the caller may hold GL contexts or threads; not
        multiprocessing's spawn, which re-imports the caller's main script), talking over a socket pair."""
        a, b = socket.socketpair()
        keep = (b.fileno(),) if self._block.fd is None else (b.fileno(), self._block.fd)  # the block by its number
        proc = subprocess.Popen(
            [sys.executable, "-c", "import app.audio_rt.worker as w; w.main()", str(b.fileno())],
            pass_fds=keep, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            env={**os.environ, **_SINGLE_THREADED, **HEAP_ENV})
        b.close()
        conn = Connection(a.detach())
        conn.send(payload)
        return proc, conn

    def stop(self) -> None:
        """Stop the stream and the worker (a worker that does not answer is killed)."""
        if self._conn is None:
            return
        if self.state == "running":
            try:
                self._conn.send(("stop",))
                deadline = time.monotonic() + 5.0
                while time.monotonic() < deadline:
                    m = self._wait(deadline - time.monotonic())
                    if m is None or m[0] in ("stopped", "lost"):
                        break
            except (OSError, EOFError):
                pass
        if self._rconn is not None:
            try:
                self._rconn.send(("stop",))
                self._wait(5.0, self._rconn, self._rproc)
            except (OSError, EOFError):
                pass
        self._kill()
        if self.state == "running":
            self.state = "stopped"

    def reopen(self) -> dict:
        """Open a new stream after a device loss or a stop (the telemetry starts again)."""
        self.stop()
        self.state = "stopped"
        return self.start()

    def _kill(self) -> None:
        for conn in (self._conn, self._rconn):  # first: a worker still waiting for orders reads the end and exits
            if conn is not None:
                conn.close()
        for proc in (self._proc, self._rproc):  # a worker that does not exit within 3 s is killed
            if proc is not None:
                try:
                    proc.wait(timeout=3.0)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(timeout=3.0)
        if self._thread is not None:
            self._thread.join(timeout=3.0)
        if self._blas:
            _OneBlasThread.release()
            self._blas = False
        self._proc = self._rproc = self._thread = self._conn = self._rconn = None

    def _wait(self, timeout: float, conn=None, proc=None):
        """The next message of the stream's worker (or of ``conn``/``proc``), or None after ``timeout`` s or when
        the worker died without one."""
        conn, proc = (self._conn, self._proc) if conn is None else (conn, proc)
        deadline = time.monotonic() + max(timeout, 0.0)
        while True:
            try:
                if conn.poll(min(0.05, max(deadline - time.monotonic(), 0.0))):
                    return conn.recv()
            except (EOFError, OSError):
                return None
            if proc is not None and proc.poll() is not None and not conn.poll(0):
                return None
            if time.monotonic() >= deadline:
                return None

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.stop()

    # --- per frame ----------------------------------------------------------------------------------------------
    def set_poses(self, head, robots=(), sources=None, gains=None, doors=None, hands=None, sidetone=None,
                  t: float | None = None) -> None:
        """Hand one frame of poses to the audio side (never blocks). head: (x, y, z, yaw[, pitch]); robots:
        (x, y, z, yaw) each; sources: (x, y, z) each (default: where they were set up); doors: open fractions."""
        sc = self.scene
        v = self.pose_layout.frame(
            time.monotonic() - self._t0 if t is None else t, head, hands=hands, robots=robots,
            sources=[s.position for s in sc.sources] if sources is None else sources,
            gains=[s.gain for s in sc.sources] if gains is None else gains,
            doors=self._door_values if doors is None else doors,
            sidetone=self.cfg.sidetone if sidetone is None else sidetone)
        self._door_values = v[self.pose_layout.DOORS].copy()
        if self.state == "running":
            self.sh.poses.write(v)

    def read_ears(self, listener: int = 0, max_frames: int | None = None) -> np.ndarray:
        """(2, n) float32 heard by listener 0 (the user: exactly what was sent to the output) or a robot (1..)
        since the last call."""
        return self.sh.ears[listener].read(max_frames)

    def read_mic(self, max_frames: int | None = None) -> np.ndarray:
        """(n,) float32 microphone samples since the last call."""
        return self.sh.mic.read(max_frames)[0]

    def poll(self) -> list[str]:
        """New problems since the last call (callback errors, device loss, a dead worker), as one-line messages.
        The audio side never raises into the application: this is where it learns of them."""
        new = []
        if self._conn is not None and self.state == "running":
            try:
                while self._conn.poll(0):
                    m = self._conn.recv()
                    if m[0] == "lost":
                        self.state = "lost"
                        new.append(f"audio device lost: {m[1]}; the application goes on without sound, "
                                   f"call reopen() (or restart the audio server) to resume")
            except (EOFError, OSError):
                pass
            if self.state == "running" and self._proc is not None and self._proc.poll() is not None:
                self.state = "lost"
                new.append(f"the audio worker exited (code {self._proc.returncode}); call reopen() to resume")
            if self.state == "running" and self._rproc is not None and self._rproc.poll() is not None:
                self.state = "lost"
                new.append(f"the robot listeners' audio process exited (code {self._rproc.returncode}); "
                           f"call reopen() to resume")
        if hasattr(self, "sh"):
            n = int(self.sh.tele[C.ERRORS])
            if n > self._errors_seen:
                new.append(f"audio callback error ({n - self._errors_seen} block(s) played silence): "
                           f"{self.sh.error_text()}")
                self._errors_seen = n
        self.events += new
        return new

    def check(self) -> None:
        """Raise the first new problem as an error (for commands that must not go on without audio)."""
        for e in self.poll():
            raise (E.DeviceError if "lost" in e or "exited" in e else E.AudioCallbackError)(e)

    def inject_faults(self, blocks: int = 1) -> None:
        """Test hook: the next ``blocks`` callbacks raise inside their body."""
        self.sh.tele[C.FAULTS] = blocks

    def mark(self) -> None:
        """Start a measurement window: :meth:`telemetry` counts from here."""
        self._mark = self.sh.tele.copy()

    def wait_callbacks(self, n: int, timeout: float = 10.0) -> int:
        """Wait until ``n`` more callbacks have run (or the timeout); returns how many did."""
        c0 = int(self.sh.tele[C.CALLBACKS])
        deadline = time.monotonic() + timeout
        while int(self.sh.tele[C.CALLBACKS]) - c0 < n and time.monotonic() < deadline and self.state == "running":
            time.sleep(0.005)
            self.poll()
        return int(self.sh.tele[C.CALLBACKS]) - c0

    def wait_settled(self, quiet: int = 100, timeout: float = 5.0) -> float:
        """Wait until ``quiet`` callbacks in a row ran without an xrun (a change of the audio server's graph, such
        as wiring a loopback, may cost the cycle in which it happens); returns the seconds it took."""
        t0 = time.monotonic()
        while time.monotonic() - t0 < timeout:
            x = int(self.sh.tele[C.XRUNS])
            if self.wait_callbacks(quiet, timeout) < quiet:
                break
            if int(self.sh.tele[C.XRUNS]) == x:
                break
        return time.monotonic() - t0

    def threads(self) -> dict:
        """{pid or thread id: role} of the pipeline's processes and its callback thread (for reports of where the
        CPU went): 'audio worker', 'robots worker', 'callback'."""
        out = {}
        for proc, role in ((self._proc, "audio worker"), (self._rproc, "robots worker")):
            if proc is not None:
                out[proc.pid] = role
        sh = getattr(self, "sh", None)
        if sh is not None and int(sh.tele[C.CB_TID]) > 0:
            out[int(sh.tele[C.CB_TID])] = "callback"
        return out

    def telemetry(self) -> dict:
        """Callback count and duration (median, p99, max), xruns from PortAudio's status flags, reported latency,
        callback errors, pose frames received; counted since :meth:`mark` (or the start)."""
        t, f = self.sh.tele.copy(), self.sh.telef
        m = getattr(self, "_mark", None)
        if m is not None:
            for k in (C.CALLBACKS, C.FRAMES, C.XRUNS, C.IN_OVERFLOW, C.OUT_UNDERFLOW, C.ERRORS, C.POSE_FRAMES,
                      C.POSE_TORN, C.ROBOT_BLOCKS, C.ROBOT_SKIPPED):
                t[k] -= m[k]
        n = int(self.sh.durations.head[0])
        first = max(n - min(int(t[C.CALLBACKS]), C.DURATIONS), 0)
        idx = np.arange(first, n) % C.DURATIONS
        d = self.sh.durations.data[0, idx].astype(np.float64) * 1000
        block_ms = 1000 * self.cfg.block / self.cfg.sample_rate
        x1 = int(self.sh.tele[C.XRUNS])
        x0 = max(x1 - int(t[C.XRUNS]), x1 - C.XRUN_LOG, 0)
        c0 = int(m[C.CALLBACKS]) if m is not None else 0
        at = [int(self.sh.xrun_at[k % C.XRUN_LOG]) for k in range(x0, x1)]
        # PortAudio splits a JACK cycle of k blocks into k callbacks and flags each of a late cycle: one xrun is the
        # cycle's first flagged block (k = 1 when the server's period is not known: each flagged block counts)
        period = (self.info or {}).get("host_period")
        k = max(1, int(period) // self.cfg.block) if period else 1
        events: list[int] = []
        for i in at:
            if not events or i - events[-1] >= k:
                events.append(i)
        unlogged = int(t[C.XRUNS]) - len(at)  # flagged blocks older than the log's XRUN_LOG: counted k to an xrun
        xruns = len(events) + (-(-unlogged // k) if unlogged > 0 else 0)
        xrun_s = [round((i - c0) * block_ms / 1000, 3) for i in events]

        def cycle_ms(j0: int, row: int = 0) -> float:  # the callbacks' time in the cycle of blocks j0 .. j0 + k - 1,
            # ms: wall (row 0) or the callback thread's CPU (row 1)
            js = range(j0, j0 + k)
            if j0 < 0 or any(n - j > C.DURATIONS or j >= n for j in js):
                return float("nan")
            return sum(float(self.sh.durations.data[row, j % C.DURATIONS]) for j in js) * 1000

        # the longer of the two cycles before each flagged one (PortAudio flags the cycle after the late one):
        # above a period, the callbacks themselves overran; below it, they were woken late or the server was. The
        # same cycle's CPU time tells an overrun of our own work (CPU near the wall time) from a callback held off
        # its CPU while it ran (CPU far below it: preempted, a vCPU the hypervisor took, a throttled cgroup)
        xrun_cb, xrun_cpu = [], []
        for i in events:
            c = [(v, j) for v, j in ((cycle_ms(i - 2 * k), i - 2 * k), (cycle_ms(i - k), i - k)) if v == v]
            if c:
                v, j = max(c)
                xrun_cb.append(round(v, 3))
                xrun_cpu.append(round(cycle_ms(j, 1), 3))
            else:
                xrun_cb.append(float("nan"))
                xrun_cpu.append(float("nan"))
        cpu = self.sh.durations.data[1, idx].astype(np.float64) * 1000
        return {
            "state": self.state, "callbacks": int(t[C.CALLBACKS]), "frames": int(t[C.FRAMES]),
            "xruns": xruns,  # late cycles of the audio server (JACK: per cycle, not per block; see cycle_blocks)
            "xrun_blocks": int(t[C.XRUNS]),  # callbacks PortAudio flagged (k per xrun on a JACK cycle of k blocks)
            "cycle_blocks": k if period else None,  # the server's cycle in blocks; None: not known (JACK not asked)
            "input_overflows": int(t[C.IN_OVERFLOW]),
            "output_underflows": int(t[C.OUT_UNDERFLOW]), "callback_errors": int(t[C.ERRORS]),
            "xrun_at_s": xrun_s,  # stream time of each xrun (the newest XRUN_LOG blocks), from the window's start
            "xrun_callback_ms": xrun_cb,  # the callbacks' time in the longer of the two cycles before each xrun, ms
            "xrun_callback_cpu_ms": xrun_cpu,  # the CPU time the callback thread got in that cycle, ms
            "block_ms": round(block_ms, 3),
            "cycle_ms": round(block_ms * k, 3),  # the period the xruns are judged against
            "callback_ms": {"median": round(float(np.median(d)), 3) if d.size else None,
                            "p99": round(float(np.percentile(d, 99)), 3) if d.size else None,
                            "max": round(float(d.max()), 3) if d.size else None},
            "callback_cpu_ms": {"median": round(float(np.median(cpu)), 3) if cpu.size else None,
                                "p99": round(float(np.percentile(cpu, 99)), 3) if cpu.size else None,
                                "max": round(float(cpu.max()), 3) if cpu.size else None},
            "callback_load_p99": round(float(np.percentile(d, 99)) / block_ms, 3) if d.size else None,
            "reported_latency_ms": {"input": round(1000 * f[C.LAT_IN], 3), "output": round(1000 * f[C.LAT_OUT], 3)},
            "pose_frames": int(t[C.POSE_FRAMES]), "pose_reads_torn": int(t[C.POSE_TORN]),
            "robot_blocks": int(t[C.ROBOT_BLOCKS]), "robot_blocks_skipped": int(t[C.ROBOT_SKIPPED]),
            "mic_blocks_nonfinite": int(t[C.MIC_NONFINITE]), "renderer_recoveries": int(t[C.RECOVERIES]),
            "callback_scheduling": _scheduling(int(t[C.CB_POLICY]), int(t[C.CB_PRIORITY]), int(t[C.CB_NICE])),
        }


def _scheduling(policy: int, priority: int, nice: int = 0) -> str | None:
    """A thread's scheduling as the worker's news words it: 'SCHED_FIFO 5', or 'time-shared (SCHED_OTHER, nice
    -20)'; None before the first callback."""
    if policy < 0:
        return None
    names = {getattr(os, n): n for n in ("SCHED_OTHER", "SCHED_FIFO", "SCHED_RR", "SCHED_BATCH", "SCHED_IDLE")
             if hasattr(os, n)}
    name = names.get(policy, f"policy {policy}")
    return f"{name} {priority}" if name in ("SCHED_FIFO", "SCHED_RR") else f"time-shared ({name}, nice {nice})"
