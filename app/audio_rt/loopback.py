"""Round-trip latency through a real audio server: our output wired back to our input, measured by correlation.

With JACK, the stream's client gets a unique name (``sonicverse-<pid>``) and its first output port is connected to
its first input port (the hardware capture ports are disconnected from it). With any other host API the test
assumes a physical loopback cable from output 1 to input 1.

The output carries, on top of the rendered scene, a 4096-sample white-noise burst every half second. The user's
ring holds exactly what was sent to the device and the microphone ring what came back, both indexed by the same
callback frame counter, so the lag of each burst's correlation peak is the round trip in samples.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import time

import numpy as np

from app.audio_rt.jack import connect_loopback
from sonicverse_core.errors import DependencyError, DeviceError


def burst_lags(sent: np.ndarray, received: np.ndarray, first_frame: int, period: int, burst: int = 4096,
               max_lag: int = 24000) -> np.ndarray:
    """Lag (samples) of each test burst (sent at stream frames k * period) between what was sent and what came
    back; both arrays start at stream frame ``first_frame``. A burst without a clear correlation peak gives NaN."""
    n = min(len(sent), len(received))
    sent, received = sent[:n].astype(np.float64), received[:n].astype(np.float64)
    nfft = 1 << int(np.ceil(np.log2(burst + max_lag)))
    lags = []
    s = (-first_frame) % period
    while s + burst + max_lag <= n:
        x = np.fft.rfft(sent[s:s + burst], nfft)
        y = np.fft.rfft(received[s:s + burst + max_lag], nfft)
        c = np.abs(np.fft.irfft(y * np.conj(x), nfft)[:max_lag])
        k = int(np.argmax(c))
        lags.append(k if c[k] > 4 * np.median(c) + 1e-12 else np.nan)
        s += period
    return np.array(lags, float)


class PlatformProbe:
    """The machine's own scheduling noise over the measurement window, the reference an xrun count is read against:
    the wake-up latency of a C thread at SCHED_FIFO 90 on every CPU, every millisecond (rt-tests' cyclictest,
    --laptop: it leaves the CPU idle states alone; -v: every wake-up, written to a file so that nothing blocks it),
    and the CPU time the hypervisor stole (/proc/stat). Nothing of ours runs above FIFO 90, so a wake-up latency
    longer than a period is the platform's (kernel or hypervisor), not the pipeline's; :meth:`attribute` says which
    xruns fell where the platform itself stalled for longer than an audio period.

    On a machine that refuses SCHED_FIFO, cyclictest cannot run (it takes a real-time priority whatever its
    ``--policy``). There a process per CPU, pinned, at nice -20 where allowed (the callback's fallback priority),
    sleeps to the same 1 ms deadlines in Python and writes the same rows. On this 2-core VM, idle, its wake-ups were
    late by 0.09-0.10 ms (median; p99 0.14-0.15 ms: the interpreter's own), and its worst in 3 s by 1.4-4.1 ms where
    cyclictest at FIFO 90 saw 0.37 ms. So it is a coarser reference: a time-shared thread is taken off its CPU now and
    then even on a quiet machine, and at nice -20 it competes with our own threads. A stall it sees is the platform's
    or a CPU shared with the pipeline. ``probe_scheduling`` says which probe ran."""

    INTERVAL_US = 1000

    def __init__(self, seconds: float, lead: float = 0.5, tail: float = 1.0):
        """Starts the probe for a window of ``seconds`` that opens ``lead`` s from now (:meth:`wait_start`); the
        probe runs ``tail`` s past the window's end. Its own start and end stay out of the window: a Python process
        per CPU starting at once, or writing its rows at once, held the callback up on a lent machine (measured: an
        xrun 11 ms into the window, and one 96 ms past its nominal end, both in a 6 ms stall seen on every CPU)."""
        import sys
        import tempfile

        from app.audio_rt.sched import NICE_CALLBACK, fifo_allowed, nice_allowed

        self.procs, self.why, self.logs, self.scheduling = [], None, [], None
        self.seconds, self.start_at = seconds, time.monotonic() + lead
        self.offset = lead  # s from the probe's own cycle 0 to the window's start
        exe = shutil.which("cyclictest")
        duration = str(int(np.ceil(lead + seconds + tail)))
        if fifo_allowed():
            if exe is None:
                self.why = "cyclictest not found: install the Debian package rt-tests"
            else:
                self.logs = [tempfile.TemporaryFile("w+")]
                self.procs = [subprocess.Popen([exe, "-m", "-p", "90", "-i", str(self.INTERVAL_US), "-d", "0", "-t",
                                                "-a", "-q", "--laptop", "-v", "-D", duration],
                                               stdout=self.logs[0], stderr=subprocess.STDOUT, text=True)]
                self.scheduling = "SCHED_FIFO 90"
        else:  # cyclictest takes a real-time priority whatever its --policy (it exits at once): a time-shared probe
            nice = NICE_CALLBACK if nice_allowed(NICE_CALLBACK) else 0
            self.offset = 0.0  # its cycle 0 is the window's start (an absolute CLOCK_MONOTONIC time)
            for cpu in sorted(os.sched_getaffinity(0)):
                self.logs.append(tempfile.TemporaryFile("w+"))
                self.procs.append(subprocess.Popen(
                    [sys.executable, "-c", _TIME_SHARED_PROBE, str(cpu), str(seconds + tail), str(self.INTERVAL_US),
                     str(nice), repr(self.start_at)],
                    stdout=self.logs[-1], stderr=subprocess.STDOUT, text=True))
            self.scheduling = f"time-shared, nice {nice} (SCHED_FIFO refused): a Python process per CPU"
        self.cpu = CpuAccount()
        self.samples = np.zeros((0, 2))  # (time s from the window's start, latency ms) of every wake-up, all CPUs

    def due(self) -> float:
        """Seconds until the window opens (a frame loop runs its frames meanwhile, then calls :meth:`wait_start`)."""
        return self.start_at - time.monotonic()

    def wait_start(self) -> None:
        """Sleep until the window opens (the caller marks its telemetry right after); the machine's CPU account
        starts here."""
        d = self.due()
        if d > 0:
            time.sleep(d)
        self.cpu = CpuAccount()

    def result(self, names: dict | None = None) -> dict:
        """The probe's figures (call once, at the window's end); ``names``: {pid or thread id: role} to name the
        busiest threads by (see :class:`CpuAccount`)."""
        cpu = self.cpu.result({**{p.pid: "probe" for p in self.procs}, **(names or {})})
        out = {"steal_ms": cpu.pop("steal_ms", None), "wakeup_ms_max": None}
        if self.procs:
            text = ""
            for proc, log in zip(self.procs, self.logs):
                try:
                    proc.wait(timeout=15)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
                log.seek(0)
                text += log.read()
                log.close()
            rows = re.findall(r"^\s*(\d+):\s*(\d+):\s*(\d+)\s*$", text, re.M)
            if rows:
                a = np.array(rows, dtype=np.int64)
                t = a[:, 1] * self.INTERVAL_US / 1e6 - self.offset  # s from the window's start
                self.span_s = (float(t.min()), float(t.max()) + self.INTERVAL_US / 1e6)  # all its wake-ups'
                keep = (t >= 0) & (t < self.seconds)  # the window's wake-ups only
                a = a[keep]
                self.samples = np.stack([t[keep], a[:, 2] / 1000.0], 1)
                out["wakeup_ms_max"] = [round(float(a[a[:, 0] == c, 2].max()) / 1000, 3)
                                        for c in np.unique(a[:, 0])]
                out["wakeups"] = int(len(a))
            else:
                self.why = f"the probe gave no result: {text.strip().splitlines()[-1:] or self.procs[0].returncode}"
        out["probe_scheduling"] = self.scheduling
        out.update(cpu)
        if self.why:
            out["why"] = self.why
        return out

    def attribute(self, xrun_at_s, period_ms: float, window_s: float = 0.1, stall_ms: float = 1.0,
                  callback_ms=None, callback_cpu_ms=None) -> dict:
        """For each xrun (seconds from the window's start) the longest platform wake-up latency within
        ``window_s`` of it; the platform's stalls (wake-ups later than ``stall_ms``, 50 times a quiet machine's
        20 us; a cluster within ``window_s`` counts once) and how many xruns fell in one (call after
        :meth:`result`). ``callback_ms`` (telemetry's ``xrun_callback_ms``, one per xrun): of the xruns outside the
        platform's stalls, how many followed a callback that itself ran longer than a period (ours) and how many
        neither (unexplained: a callback woken late, the server). ``callback_cpu_ms`` (telemetry's
        ``xrun_callback_cpu_ms``): of those that overran, how many got less CPU than a period in that cycle
        (``xruns_callback_held_off``: the thread was runnable or running and off its CPU, preempted or stalled,
        not computing)."""
        t, lat = self.samples[:, 0], self.samples[:, 1]
        worst = []
        for x in xrun_at_s:
            near = lat[np.abs(t - x) <= window_s]
            worst.append(round(float(near.max()), 3) if near.size else None)
        st = np.sort(t[lat > stall_ms])
        stalls = int(np.sum(np.diff(st) > window_s) + 1) if st.size else 0
        in_stall = [w is not None and w > stall_ms for w in worst]
        out = {"xrun_platform_ms": worst, "stall_ms": stall_ms, "platform_stalls": stalls,
               "platform_stalls_over_period": int(np.sum(lat > period_ms)), "period_ms": round(period_ms, 3),
               "xruns_in_platform_stalls": sum(in_stall)}
        if callback_ms is not None:
            over = [c is not None and c > period_ms for c in callback_ms]
            out["xruns_callback_overran"] = sum(1 for s, o in zip(in_stall, over) if o and not s)
            out["xruns_unexplained"] = sum(1 for s, o in zip(in_stall, over) if not o and not s)
            if callback_cpu_ms is not None:
                held = [c is not None and c == c and c <= period_ms for c in callback_cpu_ms]
                out["xruns_callback_held_off"] = sum(1 for s, o, h in zip(in_stall, over, held) if o and h and not s)
        return out


def _read(path: str) -> str | None:
    try:
        with open(path) as f:
            return f.read()
    except OSError:
        return None


def _threads_cpu() -> dict:
    """{(pid, tid): (process name, thread name, CPU ticks)} of every thread on the machine that can be read."""
    out = {}
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        comm = (_read(f"/proc/{pid}/comm") or "?").strip()
        try:
            tids = os.listdir(f"/proc/{pid}/task")
        except OSError:
            continue
        for tid in tids:
            st = _read(f"/proc/{pid}/task/{tid}/stat")
            if not st:
                continue
            name, rest = st[st.find("(") + 1: st.rfind(")")], st[st.rfind(")") + 2:].split()
            try:
                out[(int(pid), int(tid))] = (comm, name, int(rest[11]) + int(rest[12]))
            except (IndexError, ValueError):
                continue
    return out


class CpuAccount:
    """Where the machine's CPU went over a window, to read an xrun count against: the busy CPUs on average
    (/proc/stat, steal apart), the time some runnable thread waited for a CPU (pressure stall information,
    /proc/pressure/cpu), the time the CPU quota of this process's cgroup held every one of its threads off
    (cpu.stat's throttled time; a container's limit, invisible to the guest's idle CPUs) and its quota, and the
    threads that used the most CPU, by process and thread name (a pool spinning beside the callback shows here)."""

    def __init__(self):
        self.t0 = time.monotonic()
        self.stat0, self.psi0, self.cg0 = self._stat(), self._psi(), self._cgroup()
        self.threads0 = _threads_cpu()

    @staticmethod
    def _stat():
        text = _read("/proc/stat")
        try:
            return [int(v) for v in text.splitlines()[0].split()[1:]]
        except (AttributeError, IndexError, ValueError):
            return None

    @staticmethod
    def _psi():
        text = _read("/proc/pressure/cpu")
        m = re.search(r"^some .*total=(\d+)", text or "", re.M)
        return int(m.group(1)) if m else None

    @staticmethod
    def _cgroup():
        """(throttled periods, throttled us, quota text) of this process's cgroup, v2 or v1; None: not readable."""
        rel = ""
        for line in (_read("/proc/self/cgroup") or "").splitlines():
            parts = line.split(":", 2)
            if len(parts) == 3 and (parts[0] == "0" or "cpu" in parts[1].split(",")):
                rel = parts[2]
                break
        for base in (f"/sys/fs/cgroup{rel}", "/sys/fs/cgroup", f"/sys/fs/cgroup/cpu,cpuacct{rel}",
                     "/sys/fs/cgroup/cpu,cpuacct", "/sys/fs/cgroup/cpu"):
            text = _read(f"{base}/cpu.stat")
            if not text or "throttled" not in text:
                continue
            f = dict(line.split()[:2] for line in text.splitlines() if len(line.split()) >= 2)
            us = int(f["throttled_usec"]) if "throttled_usec" in f else int(f.get("throttled_time", 0)) // 1000
            quota = (_read(f"{base}/cpu.max") or "").strip()
            if not quota:
                q, p = _read(f"{base}/cpu.cfs_quota_us"), _read(f"{base}/cpu.cfs_period_us")
                quota = f"{q.strip()} {p.strip()}" if q and p else "?"
            return int(f.get("nr_throttled", 0)), us, quota
        return None

    def result(self, names: dict | None = None, top: int = 8) -> dict:
        """The window's figures; ``names``: {pid or thread id: role} written after the busiest threads' names."""
        names = {int(k): v for k, v in (names or {}).items()}
        dt = max(time.monotonic() - self.t0, 1e-6)
        tck = os.sysconf("SC_CLK_TCK")
        out = {"cpus": os.cpu_count()}
        s1 = self._stat()
        if self.stat0 and s1:
            d = [b - a for a, b in zip(self.stat0, s1)]
            # user nice system idle iowait irq softirq steal ...
            out["cpus_busy"] = round((d[0] + d[1] + d[2] + d[5] + d[6]) / tck / dt, 2)
            if len(d) > 7:
                out["steal_ms"] = round(d[7] * 1000 / tck, 1)  # the hypervisor's, over all CPUs
        p1 = self._psi()
        if self.psi0 is not None and p1 is not None:
            out["cpu_pressure_ms"] = round((p1 - self.psi0) / 1000, 1)
        c1 = self._cgroup()
        if self.cg0 is not None and c1 is not None:
            out["cgroup_throttled"] = c1[0] - self.cg0[0]
            out["cgroup_throttled_ms"] = round((c1[1] - self.cg0[1]) / 1000, 1)
            out["cgroup_cpu_max"] = c1[2]
        t1 = _threads_cpu()
        was = {k: v[2] for k, v in self.threads0.items()}  # a thread born in the window: all its CPU is the window's
        used = sorted(((v[2] - was.get(k, 0), v[0], v[1], k) for k, v in t1.items() if v[2] > was.get(k, 0)),
                      reverse=True)

        def who(k) -> str:
            role = [names[i] for i in dict.fromkeys(k) if i in names]  # the process's role, then the thread's
            return f" ({', '.join(role)})" if role else ""

        out["threads_top_cpus"] = [f"{comm}/{name}[{k[1]}]{who(k)}: {ticks / tck / dt:.2f}"
                                   for ticks, comm, name, k in used[:top]]
        return out


# the time-shared probe's body: argv cpu, seconds, interval in us, nice, start (time.monotonic(), the same clock in
# every process); one row 'cpu: cycle: lateness us' a wake-up, cycle 0 due at the start
_TIME_SHARED_PROBE = """
import gc, os, sys, time
cpu, seconds, interval, nice = int(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
os.sched_setaffinity(0, {cpu})
if nice:
    os.setpriority(os.PRIO_PROCESS, 0, nice)
gc.disable()
n, step, clock, sleep = int(seconds * 1e6) // interval, interval / 1e6, time.monotonic, time.sleep
late = [0] * n
t0 = float(sys.argv[5])
for k in range(n):
    due = t0 + k * step
    d = due - clock()
    if d > 0:
        sleep(d)
    late[k] = int((clock() - due) * 1e6)
sys.stdout.write("".join(f"{cpu}:{k}:{v}\\n" for k, v in enumerate(late)))
"""


def random_sources(spec: str | None, n: int, seed: int = 0, gain: float = 0.05):
    """n sound-bank sources on random navigable points of the scene (a 6 m circle in free field)."""
    from app.audio_rt.config import SourceSpec
    from assets_manifest import soundbank

    rng = np.random.default_rng(seed)
    if spec is None:
        a = rng.uniform(0, 2 * np.pi, n)
        pts = np.stack([3 * np.cos(a), 3 * np.sin(a)], 1)
        head = (0.0, 0.0, 1.6, 0.0, 0.0)
    else:
        from sonicverse_core.geometry.navgrid import NavGrid
        from sonicverse_core.scene.spec import load_scene

        scene = load_scene(spec)
        pts = NavGrid(scene).sample(rng, n + 1)
        head = (float(pts[-1, 0]), float(pts[-1, 1]), scene.floor_z + 1.6, 0.0, 0.0)
    cats = soundbank.CATEGORIES
    srcs = [SourceSpec(f"{cats[i % len(cats)]}/{i % 3}", (float(pts[i, 0]), float(pts[i, 1]), 1.0), gain)
            for i in range(n)]
    return srcs, head


def loopback_test(seconds: float = 10.0, sources: int = 16, spec: str | None = "builtin:apartment",
                  mode: str = "process", load: str = "none", robots: int = 1, device=None,
                  sample_rate: int = 48000, block: int = 256, view: int = 512, seed: int = 0,
                  progress=None, door_every: float | None = None) -> dict:
    """Open the duplex stream with the scene, wire its output to its input, run for ``seconds`` while the frame
    loop hands poses at frame rate (load='frames': it also renders stereo views as fast as it can), and measure
    round trip, xruns and callback timing. ``door_every``: every that many seconds the frame loop opens or shuts
    one of the scene's doors (each in turn), as a VR user's trigger does (``door_moves`` counts them)."""
    from app.audio_rt.config import AudioConfig, AudioScene
    from app.audio_rt.engine import AudioEngine
    from sonicverse_core.errors import ConfigError

    if not (0.5 <= seconds <= 3600) or not (0 <= sources <= 1024) or load not in ("none", "frames"):
        raise ConfigError("--seconds must be 0.5-3600, --sources 0-1024, --load none or frames")
    srcs, head = random_sources(spec, sources, seed)
    n_doors = 0
    if door_every is not None:
        from sonicverse_core.scene.spec import load_scene

        n_doors = len(load_scene(spec).doors) if spec else 0
        if not n_doors:
            raise ConfigError(f"--door-every: {spec or 'the free field'} has no doors")
    robo = [(head[0] + 1.0, head[1], 0.4, 180.0)] * robots
    cfg = AudioConfig(device=device, sample_rate=sample_rate, block=block, mode=mode, test_signal=True,
                      ring_seconds=4.0)
    eng = AudioEngine(cfg, AudioScene(spec, sources=srcs, robots=robo, head=head))
    vis = None
    if load == "frames":
        from app.scene.visual import VisualScene
        from sonicverse_core.scene.spec import load_scene

        vis = VisualScene(load_scene(spec) if spec else _empty_scene(), view, view)
        vis.render_stereo(head[:4])  # compile shaders before the clock starts
    info = eng.start()
    try:
        client = info.get("jack_client")
        wired = connect_loopback(client) if client else ("output 1", "input 1 (cable)")
        eng.set_poses(head, robots=robo, t=0.0)  # the frame loop runs before the window opens: no first-pose jump
        settle = eng.wait_settled()  # the JACK graph change itself may cost a cycle: start counting after it
        probe = PlatformProbe(seconds)
        probe.wait_start()
        eng.mark()
        mic_ring, out_ring = eng.sh.mic, eng.sh.ears[0]
        first = min(int(mic_ring.head[0]), int(out_ring.head[0]))
        mic_ring.read_pos = out_ring.read_pos = first
        sent, back, frames = [], [], []
        t0 = time.perf_counter()
        t = 0.0
        doors, moves = (eng._door_values.copy() if n_doors else None), 0
        while t < seconds:
            yaw = 30.0 * t
            h = (head[0] + 0.3 * np.sin(0.5 * t), head[1] + 0.3 * np.cos(0.5 * t), head[2], yaw, 0.0)
            if n_doors and t >= (moves + 1) * door_every:  # a door opens or shuts (each in turn)
                k = moves % n_doors
                doors[k] = 0.0 if doors[k] > 0.5 else 1.0
                moves += 1
            eng.set_poses(h, robots=robo, t=t, doors=doors)
            if vis is not None:
                vis.render_stereo(h[:4])
            else:
                time.sleep(1 / 90)  # a frame loop paced at 90 Hz that renders nothing
            sent.append(out_ring.read()[0])
            back.append(mic_ring.read()[0])
            for r in eng.sh.ears[1:]:
                r.skip_to_end()
            for e in eng.poll():
                if progress:
                    progress(e)
            t1 = time.perf_counter()
            frames.append(t1 - t0 - t)
            t = t1 - t0
        tele = eng.telemetry()
        platform = probe.result({os.getpid(): "main", **eng.threads()})
        platform.update(probe.attribute(tele["xrun_at_s"], tele["cycle_ms"], callback_ms=tele["xrun_callback_ms"],
                                        callback_cpu_ms=tele["xrun_callback_cpu_ms"]))
    finally:
        eng.stop()
        if vis is not None:
            vis.close()
    from app.audio_rt.core import burst_period

    period = burst_period(sample_rate, block)
    lags = burst_lags(np.concatenate(sent), np.concatenate(back), first, period)
    ok = lags[np.isfinite(lags)]
    fr = np.array(frames[1:]) * 1000
    block_ms = 1000 * block / sample_rate
    return {
        "bench": "audio-loopback", "mode": mode, "load": load, "scene": spec, "sources": sources,
        "robots": robots, "seconds": round(t, 2), "device": info["output_device"], "hostapi": info["hostapi"],
        "wired": list(wired), "sample_rate": sample_rate, "block": block, "block_ms": round(block_ms, 3),
        "round_trip_ms": round(float(np.median(ok)) * 1000 / sample_rate, 3) if ok.size else None,
        "round_trip_ms_max": round(float(np.max(ok)) * 1000 / sample_rate, 3) if ok.size else None,
        "round_trip_bursts": int(ok.size), "round_trip_missed": int(lags.size - ok.size),
        "round_trip_periods": round(float(np.median(ok)) / block, 3) if ok.size else None,
        "settle_s": round(settle, 3), "xruns": tele["xruns"], "xrun_at_s": tele["xrun_at_s"],
        "xrun_callback_ms": tele["xrun_callback_ms"], "xrun_callback_cpu_ms": tele["xrun_callback_cpu_ms"],
        "callbacks": tele["callbacks"], "callback_errors": tele["callback_errors"], "robot_blocks": tele["robot_blocks"],
        "robot_blocks_skipped": tele["robot_blocks_skipped"],
        "callback_p99_ms": tele["callback_ms"]["p99"], "callback_ms": tele["callback_ms"],
        "callback_cpu_ms": tele["callback_cpu_ms"],
        "reported_latency_ms": tele["reported_latency_ms"], "platform": platform,
        "cpu_latency_request": info.get("cpu_latency_request"),
        "frames": len(fr), "frame_ms_p50": round(float(np.median(fr)), 2) if fr.size else None,
        "frame_ms_p99": round(float(np.percentile(fr, 99)), 2) if fr.size else None,
        "view": [2, view, view] if load == "frames" else None, "subsystems": info["subsystems"],
        "door_every_s": door_every, "door_moves": moves,
    }


def _empty_scene():
    from sonicverse_core.scene.spec import load_scene

    return load_scene("shoebox:8x8x3")
