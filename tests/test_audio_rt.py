"""Real-time audio pipeline: lock-free structures, pose interpolation, and the duplex stream on a real clocked
JACK server (dummy backend) with our output wired to our input."""
import dataclasses
import glob
import json

import numpy as np
import pytest

from app.audio_rt.config import AudioConfig, AudioScene, SourceSpec
from app.audio_rt.poses import PoseInterpolator, PoseLayout, mouth
from app.audio_rt.shared import Layout, Ring, SeqLock, SharedBlock
from sonicverse_core.errors import ConfigError, DeviceError, PoseError

FS, B = 48000, 256
SCENE = "shoebox:6x5x3"


# --- lock-free structures ---------------------------------------------------------------------------------------
def _views(**entries):
    L = Layout()
    for k, (shape, dt) in entries.items():
        L.add(k, shape, dt)
    return L.views(SharedBlock(L.size, private=True).buf)


def test_ring_wraps_in_order_and_counts_what_a_slow_reader_lost():
    v = _views(d=((2, 1000), np.float32), h=(1, np.int64))
    w, r = Ring(v["d"], v["h"]), Ring(v["d"], v["h"])
    x = np.arange(2 * 2600, dtype=np.float32).reshape(2, 2600)
    for i in range(0, 700, 100):
        w.write(x[:, i:i + 100])
    assert np.array_equal(r.read(), x[:, :700])
    for i in range(700, 2600, 100):  # 1900 more frames: the reader is 900 frames over the capacity
        w.write(x[:, i:i + 100])
    got = r.read()
    assert r.lost == 900 and np.array_equal(got, x[:, 1600:2600])


def test_ring_shared_between_two_mappings_of_one_block():
    L = Layout()
    L.add("d", (1, 64), np.float32)
    L.add("h", 1, np.int64)
    a = SharedBlock(L.size)
    b = SharedBlock(L.size, a.path, create=False)
    a.release()  # both keep their mapping
    wa, rb = L.views(a.buf), L.views(b.buf)
    reader = Ring(rb["d"], rb["h"])  # a reader starts at the current head
    Ring(wa["d"], wa["h"]).write(np.ones((1, 10), np.float32))
    assert np.array_equal(reader.read(), np.ones((1, 10)))


def test_the_shared_block_has_no_name_and_a_worker_maps_it_by_its_descriptor():
    """A session killed at any moment (session 65: ``kill -9`` while a worker started) must leave nothing in
    /dev/shm: the block is never named, and a worker started with its descriptor maps the same memory."""
    import os
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    def named() -> list:
        return [p for d in ("/dev/shm", tempfile.gettempdir()) for p in Path(d).glob("sonicverse-audio*")]

    before = named()
    a = SharedBlock(4096)
    assert named() == before == []
    np.frombuffer(a.buf, np.uint8)[:4] = (1, 2, 3, 4)
    code = ("import sys; import numpy as np; from app.audio_rt.shared import SharedBlock; "
            "b = SharedBlock(4096, sys.argv[1], create=False); v = np.frombuffer(b.buf, np.uint8); "
            "print(list(v[:4])); v[4] = 9")
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", code, a.path], pass_fds=(a.fd,), cwd=root, capture_output=True,
                         text=True, env={**os.environ, "PYTHONPATH": str(root)})
    assert out.returncode == 0 and out.stdout.split("\n")[0] == "[1, 2, 3, 4]", out.stderr[-500:]
    assert a.buf[4] == 9  # the worker's write is the creator's memory
    # without the descriptor kept, the path names nothing there (a worker gets the block only as ``_spawn`` gives it)
    out = subprocess.run([sys.executable, "-c", code, a.path], cwd=root, capture_output=True, text=True,
                         env={**os.environ, "PYTHONPATH": str(root)})
    assert not (out.returncode == 0 and out.stdout.split("\n")[0] == "[1, 2, 3, 4]")
    a.release()
    assert a.fd is None and a.buf[4] == 9  # the mapping outlives the descriptor
    assert named() == []


def test_seqlock_never_returns_a_torn_frame():
    v = _views(s=(1, np.int64), d=(8, np.float64))
    w, r = SeqLock(v["s"], v["d"]), SeqLock(v["s"], v["d"])
    out = np.zeros(8)
    w.write(np.full(8, 1.0))
    assert r.read_into(out) == 1 and np.all(out == 1)
    assert r.read_into(out) == 0  # nothing new
    v["s"][0] += 1  # a writer stopped half-way: odd sequence, half-written payload
    v["d"][:4] = 2.0
    assert r.read_into(out) == -1 and np.all(out == 1)  # the previous frame is kept
    v["s"][0] += 1
    assert r.read_into(out) == 1 and np.all(out[:4] == 2) and np.all(out[4:] == 1)


# --- poses ------------------------------------------------------------------------------------------------------
def test_pose_frame_rejects_nan_and_bad_counts():
    L = PoseLayout(n_robots=1, n_sources=2, n_doors=1)
    ok = L.frame(0.0, (1, 2, 1.6, 90), robots=[(0, 0, 0.4, 0)], sources=[(1, 1, 1), (2, 2, 1)], doors=[0.5])
    assert ok.shape == (L.size,) and ok[L.DOORS][0] == 0.5
    with pytest.raises(PoseError, match="not finite"):
        L.frame(0.0, (1, np.nan, 1.6, 90), robots=[(0, 0, 0.4, 0)], sources=[(1, 1, 1), (2, 2, 1)], doors=[0])
    with pytest.raises(PoseError, match="robot"):
        L.frame(0.0, (1, 2, 1.6, 90), robots=[], sources=[(1, 1, 1), (2, 2, 1)], doors=[0])
    with pytest.raises(PoseError, match="door"):
        L.frame(0.0, (1, 2, 1.6, 90), robots=[(0, 0, 0.4, 0)], sources=[(1, 1, 1), (2, 2, 1)], doors=[1.5])


def test_interpolation_ramps_over_the_frame_interval_the_short_way_round_and_jumps_on_teleport():
    L = PoseLayout()
    ip = PoseInterpolator(L)
    blk = B / FS
    ip.new_frame(L.frame(0.0, (0, 0, 1.6, 350)))
    for k in range(1, 4):  # frames at 90 Hz teach it the interval
        ip.new_frame(L.frame(k / 90, (0, 0, 1.6, 350)))
        for _ in range(2):
            ip.advance(blk)
    ip.new_frame(L.frame(4 / 90, (0.05, 0, 1.6, 10)))  # +5 cm and 20 degrees through north
    seen = [ip.advance(blk)[L.HEAD].copy() for _ in range(3)]
    assert 0 < seen[0][0] < seen[1][0] <= 0.05  # moves in steps, not at once
    assert np.isclose(seen[-1][0], 0.05) and np.isclose(seen[-1][3] % 360, 10)
    assert all(350 <= s[3] <= 370 for s in seen)  # never swept backwards through 180
    ip.new_frame(L.frame(5 / 90, (5.0, 0, 1.6, 10)))  # 5 m in one frame: a teleport
    assert np.isclose(ip.advance(blk)[1], 5.0)


def test_mouth_is_in_front_of_and_below_the_ears():
    m, fwd = mouth(np.array([1.0, 2.0, 1.6, 90.0, 0.0]))
    assert np.allclose(fwd, [0, 1, 0], atol=1e-12) and np.isclose(m[1] - 2.0, 0.08) and m[2] < 1.6


def test_listener_that_excludes_a_source_hears_none_of_it():
    from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig

    r = AcousticRenderer(None, RenderConfig(late_reverb=False, early_reflections=False))
    s = r.add_source(np.random.default_rng(0).normal(size=FS).astype(np.float32) * 0.1, (2, 0, 1.6))
    r.add_listener((0, 0, 1.6))
    deaf = r.add_listener((0, 0, 1.6), exclude=[s])
    a, b = r.render(0.2)
    assert np.sqrt(np.mean(a ** 2)) > 1e-3 and np.max(np.abs(b)) == 0.0
    r.set_heard(deaf, s, True)
    assert np.max(np.abs(r.render(0.1)[1])) > 1e-3


def test_config_rejects_bad_settings():
    with pytest.raises(ConfigError):
        AudioConfig(block=300)
    with pytest.raises(ConfigError):
        AudioConfig(mode="fiber")
    with pytest.raises(ConfigError):
        AudioConfig(sample_rate=4000)


def test_callback_logs_when_each_xrun_happened_and_keeps_the_mic_ring_in_step():
    """PortAudio's status flags are counted and stamped with the callback index (telemetry's xrun_at_s) and with
    the longest of the two callbacks before (xrun_callback_ms: did the callback itself overrun?); a failing
    block still advances the microphone ring, which the robots' process follows frame for frame."""
    import sounddevice as sd

    from app.audio_rt import config as C
    from app.audio_rt.core import AudioCore, Shared

    eng = _engine()
    eng.sh = Shared(eng.layout, SharedBlock(eng.layout.size, private=True).buf, eng.n_listeners)
    core = AudioCore(eng.cfg, dataclasses.replace(eng.scene, spec=None), eng.sh, eng.pose_layout, role="user")
    ind, outd = np.zeros((B, 1), np.float32), np.zeros((B, 2), np.float32)
    for k in range(10):
        if k == 6:
            eng.sh.tele[C.FAULTS] = 1
        flags = sd.CallbackFlags(0x4 if k in (3, 7) else 0)  # paOutputUnderflow
        core.callback(ind, outd, B, None, flags)
    eng.sh.durations.data[0, 2] = 0.009  # callback 2 overran (9 ms): the xrun flagged in callback 3 is its
    tele = eng.telemetry()
    assert tele["xruns"] == 2 and tele["output_underflows"] == 2 and tele["callback_errors"] == 1
    np.testing.assert_allclose(tele["xrun_at_s"], [3 * B / FS, 7 * B / FS], atol=1e-3)
    assert tele["xrun_callback_ms"][0] == 9.0 and 0 < tele["xrun_callback_ms"][1] < 1000 * B / FS
    assert int(eng.sh.mic.head[0]) == int(eng.sh.tele[C.FRAMES]) == 10 * B
    assert len(core.r.listeners) == 1  # role 'user': the robots are rendered elsewhere
    assert tele["cycle_blocks"] is None and tele["xrun_blocks"] == 2 and tele["cycle_ms"] == tele["block_ms"]
    # a JACK cycle of two blocks (--jack-period 512): PortAudio calls back twice a cycle and flags both callbacks of
    # a late cycle. Measured on a JACK dummy server at 512: the flags come in pairs 5.3 ms apart. One xrun each.
    eng.info = {"host_period": 2 * B}
    eng.mark()
    for k in range(12):
        core.callback(ind, outd, B, None, sd.CallbackFlags(0x4 if k in (4, 5, 8, 9) else 0))
    c0 = 10  # callbacks before the mark
    dur = eng.sh.durations.data[0]
    dur[c0:c0 + 12] = 0.001
    dur[c0 + 2], dur[c0 + 3] = 0.004, 0.005  # the cycle before the first xrun: 9 ms, under the 10.7 ms period
    dur[c0 + 6] = 0.011  # the cycle before the second: 12 ms, over it
    cpu = eng.sh.durations.data[1]
    cpu[c0:c0 + 12] = 0.001
    cpu[c0 + 2], cpu[c0 + 3] = 0.004, 0.005  # 9 ms of CPU in 9 ms: it computed all along
    cpu[c0 + 6] = 0.002  # 3 ms of CPU in 12 ms: held off its CPU for 9
    tele = eng.telemetry()
    np.testing.assert_allclose(tele["xrun_callback_cpu_ms"], [9.0, 3.0], atol=1e-3)
    assert tele["callback_cpu_ms"]["max"] == pytest.approx(5.0, abs=1e-3)
    assert tele["xrun_blocks"] == 4 and tele["xruns"] == 2 and tele["cycle_blocks"] == 2
    assert tele["cycle_ms"] == pytest.approx(2 * 1000 * B / FS, abs=1e-3)
    np.testing.assert_allclose(tele["xrun_at_s"], [4 * B / FS, 8 * B / FS], atol=1e-3)
    np.testing.assert_allclose(tele["xrun_callback_ms"], [9.0, 12.0], atol=1e-3)
    # two late cycles in a row are two xruns, not one run of four flagged blocks
    eng.mark()
    for k in range(8):
        core.callback(ind, outd, B, None, sd.CallbackFlags(0x4 if k in (2, 3, 4, 5) else 0))
    assert eng.telemetry()["xruns"] == 2


def test_cpu_account_names_the_busy_threads():
    """Where the window's CPU went: a thread of this process that spins for the whole window shows as the busiest,
    named by the role given, using about one CPU; the machine's busy CPUs count it."""
    import os
    import threading
    import time

    from app.audio_rt.loopback import CpuAccount

    acc = CpuAccount()
    tid, spun, done = [], threading.Event(), threading.Event()

    def spin():
        tid.append(threading.get_native_id())
        end = time.thread_time() + 0.4
        while time.thread_time() < end:  # 0.4 s of this thread's own CPU, however the machine shares it out
            pass
        spun.set()
        done.wait()  # alive when the account closes (a thread gone by then is not in /proc to be counted)

    t = threading.Thread(target=spin)
    t.start()
    spun.wait()
    res = acc.result({os.getpid(): "main", tid[0]: "spinner"})
    done.set()
    t.join()
    top = [r for r in res["threads_top_cpus"] if f"[{tid[0]}] (main, spinner)" in r]
    assert top, res["threads_top_cpus"]
    assert res["cpus"] == os.cpu_count() and res["cpus_busy"] > 0
    assert res.get("cgroup_throttled_ms", 0) >= 0 and res.get("cpu_pressure_ms", 0) >= 0


def test_platform_probe_and_realtime_settings():
    """The loopback test's reference for the machine's own noise: cyclictest's worst wake-up latency per CPU at
    FIFO 90 and the stolen time; the heap kept and the CPU latency request are best effort, never silent."""
    import os

    from app.audio_rt.heap import keep_heap
    from app.audio_rt.loopback import PlatformProbe
    from app.audio_rt.qos import LatencyRequest

    probe = PlatformProbe(1.0)
    res = probe.result()
    assert "why" not in res, res  # rt-tests is a system dependency: missing, this fails
    assert res["probe_scheduling"] == "SCHED_FIFO 90", res  # this machine allows it (the lent ones did not)
    # every wake-up of every CPU, 1 ms apart: about 1,000 per CPU in a second
    assert 0.8 * os.cpu_count() * 1000 <= res["wakeups"] == len(probe.samples) <= 1.1 * os.cpu_count() * 1000
    assert 0 <= probe.samples[:, 0].min() and probe.samples[:, 0].max() <= 1.1
    assert np.isclose(probe.samples[:, 1].max(), max(res["wakeup_ms_max"]))
    # attribution, on samples made up: a 6 ms stall at 2.0 s (two wake-ups), a 1.5 ms one at 5.0 s
    probe.samples = np.array([[t / 1000, 0.02] for t in range(8000)])
    probe.samples[2000, 1], probe.samples[2001, 1], probe.samples[5000, 1] = 6.0, 5.5, 1.5
    a = probe.attribute([2.05, 3.5, 5.01], period_ms=5.333)
    assert a["xrun_platform_ms"] == [6.0, 0.02, 1.5] and a["xruns_in_platform_stalls"] == 2
    assert "xruns_callback_overran" not in a
    # the xrun at 3.5 s, outside the stalls, after a callback of 7 ms: ours; at 2.05 s it is the platform's
    a = probe.attribute([2.05, 3.5, 5.01], period_ms=5.333, callback_ms=[9.0, 7.0, 1.0])
    assert a["xruns_callback_overran"] == 1 and a["xruns_unexplained"] == 0
    a = probe.attribute([2.05, 3.5, 5.01], period_ms=5.333, callback_ms=[9.0, 1.0, 1.0])
    assert a["xruns_callback_overran"] == 0 and a["xruns_unexplained"] == 1
    # the callback at 3.5 s ran 7 ms with 2 ms of CPU: held off its CPU; with 6 ms of CPU it computed
    a = probe.attribute([2.05, 3.5, 5.01], period_ms=5.333, callback_ms=[9.0, 7.0, 1.0], callback_cpu_ms=[9, 2, 1])
    assert a["xruns_callback_overran"] == 1 and a["xruns_callback_held_off"] == 1
    a = probe.attribute([2.05, 3.5, 5.01], period_ms=5.333, callback_ms=[9.0, 7.0, 1.0], callback_cpu_ms=[9, 6, 1])
    assert a["xruns_callback_overran"] == 1 and a["xruns_callback_held_off"] == 0
    assert a["platform_stalls"] == 2 and a["platform_stalls_over_period"] == 2
    assert len(res["wakeup_ms_max"]) == os.cpu_count() and all(0 < m < 1000 for m in res["wakeup_ms_max"])
    assert res["steal_ms"] is None or res["steal_ms"] >= 0
    assert keep_heap() and keep_heap()  # glibc here; idempotent
    q = LatencyRequest(0)
    assert q.held or q.why.startswith("/dev/cpu_dma_latency")
    q.release()
    assert not q.held


# --- the stream on a real clocked server ------------------------------------------------------------------------
def _engine(**kw):
    from app.audio_rt.engine import AudioEngine

    scene = AudioScene(SCENE, sources=[SourceSpec("sofa/0", (4.0, 3.0, 1.2), 0.1)], robots=[(1.5, 1.0, 0.4, 0.0)],
                       head=(2.0, 2.5, 1.6, 0.0, 0.0))
    return AudioEngine(AudioConfig(**{"test_signal": True, **kw}), scene)


@pytest.fixture(scope="module")
def running(jack):
    """One engine for the module's stream tests: output wired to input."""
    from app.audio_rt.jack import connect_loopback

    eng = _engine()
    info = eng.start()
    connect_loopback(info["jack_client"])
    assert eng.wait_callbacks(50) >= 50
    yield eng
    eng.stop()


def test_round_trip_is_two_server_periods_and_the_mic_reaches_the_robot(running):
    from app.audio_rt.core import burst_period
    from app.audio_rt.loopback import burst_lags

    eng = running
    mic, out, robot = eng.sh.mic, eng.sh.ears[0], eng.sh.ears[1]
    first = min(int(mic.head[0]), int(out.head[0]))
    mic.read_pos = out.read_pos = robot.read_pos = first
    sent, back, heard = [], [], []
    period = burst_period(FS, B)
    # four periods: burst_lags needs burst + max_lag (a period) after each burst's start, and the first burst starts
    # anywhere in the first period, so three periods held only one whole burst for about half the start phases
    for _ in range(400):  # bounded: a stream that stopped fails here with its telemetry, not at the suite's timeout
        if sum(len(x) for x in sent) >= 4 * period:
            break
        assert eng.wait_callbacks(20) > 0, (eng.poll(), eng.events, eng.telemetry())
        eng.set_poses((2.0, 2.5, 1.6, 0.0, 0.0), robots=[(1.5, 1.0, 0.4, 0.0)])
        sent.append(out.read()[0])
        back.append(mic.read()[0])
        heard.append(robot.read())
    sent, back = np.concatenate(sent), np.concatenate(back)
    lags = burst_lags(sent, back, first, period)
    assert len(lags) >= 2 and np.all(np.isfinite(lags))
    rt_ms = np.max(lags) / FS * 1000
    assert rt_ms <= 2 * B / FS * 1000 + 1.0, rt_ms  # two server periods + 1 ms: nothing added by us
    assert np.array_equal(back[512:], sent[:-512]) or np.max(lags) == np.min(lags)
    heard = np.concatenate(heard, axis=1)
    assert np.all(np.isfinite(heard)) and np.max(np.abs(heard)) <= 1.0 and np.sqrt(np.mean(heard ** 2)) > 1e-4
    # the robot renders in its own process, in step with the stream: the microphone's bursts reach its ears at one
    # lag (a robot block rendered out of step, or a skipped one, would move it by 256 samples). Seen once in ~10
    # runs: the first burst after the start gave a spurious peak (59 samples, shorter than the flight time), so one
    # burst may disagree. The ear's response has lobes a few samples apart (the HRTF): a burst's correlation may peak
    # on either (seen: 316 and 325 samples), so lags agree within 32 samples, far below a block's 256
    assert eng.info["robot_listeners"] == "own process"
    # whether the machine let the supervisor and the callback run at real-time priorities is news, not a silent
    # fallback; where it does, the callback (the audio server's client thread) runs above the supervisor
    sup, cb = eng.info["supervisor_scheduling"], eng.telemetry()["callback_scheduling"]
    assert sup == "SCHED_FIFO 4" or sup.startswith("time-shared, nice "), eng.info
    assert cb is not None and (cb.startswith("time-shared (") or cb.startswith("SCHED_FIFO ")), cb
    if sup == "SCHED_FIFO 4" and cb.startswith("SCHED_FIFO "):
        assert int(cb.split()[1]) > 4, (sup, cb)
    n = min(len(back), heard.shape[1])
    robot_lags = burst_lags(back[:n], heard[0, :n], first, period, max_lag=2048)
    ok = robot_lags[np.isfinite(robot_lags)]
    agree = max((int(np.sum(np.abs(ok - x) <= 32)) for x in ok), default=0)
    assert agree >= 2 and agree >= len(robot_lags) - 1, (robot_lags, eng.telemetry())
    tele = eng.telemetry()
    assert tele["robot_blocks"] >= tele["callbacks"] - 4  # the robots keep up with the stream
    assert tele["callbacks"] > 0 and tele["reported_latency_ms"]["output"] > 0
    assert tele["callback_ms"]["median"] < tele["block_ms"]


def test_poses_arrive_in_the_audio_process(running):
    n0 = running.telemetry()["pose_frames"]
    for k in range(5):
        running.set_poses((2.0, 2.5, 1.6, 10.0 * k, 0.0), robots=[(1.5, 1.0, 0.4, 0.0)])
        running.wait_callbacks(2)
    assert running.telemetry()["pose_frames"] >= n0 + 3
    with pytest.raises(PoseError):
        running.set_poses((2.0, np.inf, 1.6, 0.0, 0.0), robots=[(1.5, 1.0, 0.4, 0.0)])


def test_callback_exception_plays_silence_is_reported_and_the_stream_goes_on(running):
    eng = running
    eng.poll()
    seen = len(eng.events)
    eng.inject_faults(3)
    eng.wait_callbacks(10)  # polls too: every reported problem is kept in eng.events
    eng.poll()
    events = eng.events[seen:]
    assert events and all("injected fault" in e for e in events), events
    assert sum(int(e.split("(")[1].split(" ")[0]) for e in events) == 3  # blocks that played silence
    n = eng.telemetry()["callbacks"]
    assert eng.wait_callbacks(10) >= 10 and eng.state == "running" and eng.telemetry()["callbacks"] >= n + 10


def test_devices_that_do_not_exist_or_cannot_do_it_give_one_clear_error(jack):
    with pytest.raises(DeviceError, match="no output device 'no-such-card'.*available"):
        _engine(device="no-such-card").start()
    with pytest.raises(DeviceError, match="does not support 44100 Hz"):
        _engine(sample_rate=44100).start()


def test_mono_output_device_is_refused(private_jack):
    private_jack(playback=1)
    with pytest.raises(DeviceError, match="1 output channel; binaural audio needs 2"):
        _engine().start()


def test_device_vanishing_mid_stream_is_reported_and_the_stream_reopens(private_jack):
    srv = private_jack()
    eng = _engine()
    eng.start()
    try:
        assert eng.wait_callbacks(20) >= 20  # the poll may overshoot by one
        srv.stop()  # the audio server goes away under the stream
        # ... leaving nothing of its clients in /dev/shm (jack2's per-client futex files; 150 KB of them after a
        # suite before session 66)
        assert not glob.glob(f"/dev/shm/jack_sem.*_{srv.name}_*")
        seen = len(eng.events)
        for _ in range(400):  # the worker's supervisor notices within its stall limit
            eng.poll()
            if eng.state == "lost":
                break
            eng.wait_callbacks(1, timeout=0.05)
        events = eng.events[seen:]
        assert eng.state == "lost" and any("lost" in e or "exited" in e for e in events), events
        srv.start()
        eng.reopen()
        assert eng.state == "running" and eng.wait_callbacks(20) >= 20
    finally:
        eng.stop()


WARM_CHECK = r"""
import sys
import numpy as np
from numba.core.dispatcher import Dispatcher
from app.audio_rt.config import AudioConfig, AudioScene, SourceSpec
from app.audio_rt.core import build_renderer

def signatures():
    return {(m, k): len(v.signatures) for m, mod in list(sys.modules.items()) if m.startswith("sonicverse_core")
            for k, v in vars(mod).items() if isinstance(v, Dispatcher)}

sc = AudioScene("builtin:apartment", sources=[SourceSpec("sofa/0", (6.0, 3.0, 1.2), 0.1),
                                              SourceSpec("sofa/1", (1.0, 1.0, 1.2), 0.1)])
r, scene, mic, user, doors = build_renderer(sc, AudioConfig(), role="all")
start = np.array([4.0, 3.0, 1.6])
r.set_listener(user, start, 0.0, 0.0)
was = [d.open_fraction for d in scene.doors]
r.warm_kernels()
assert np.array_equal(user.position, start) and [d.open_fraction for d in scene.doors] == was
before = signatures()
centres = [rm.footprint.mean(axis=0) for rm in scene.rooms]
walk = [a + t * (b - a) for a, b in zip(centres, centres[1:] + centres[:1]) for t in np.linspace(0, 1, 25)]
for k, xy in enumerate(walk):  # room to room through the walls and doorways, a source and the doors moving
    r.set_listener(user, (xy[0], xy[1], 1.6), 7.0 * k, 5.0)
    r._pos[0] = (walk[-1 - k][0], walk[-1 - k][1], 1.2)
    if doors and k % 20 == 10:
        scene.set_door(doors[(k // 20) % len(doors)], 0.5)
        if r.occlusion is not None:
            r.occlusion.prepare()
    if mic is not None:
        mic.pending = np.zeros(AudioConfig().block, np.float32)
    r.render_block()
new = {k: v for k, v in signatures().items() if v != before.get(k, 0)}
print("ROOMS", len(centres), "DOORS", len(doors), "KERNELS", len(before), "NEW", sorted(new))
"""


def test_every_kernel_a_block_can_reach_compiles_before_the_stream_opens():
    """The worker's warm-up (``AcousticRenderer.warm_kernels``) leaves nothing to compile in the callback: in a fresh
    interpreter, walking from room to room of the apartment (through walls and doorways, where no room's images
    apply) with doors moving, a source crossing rooms and the head turning adds no signature to any of the
    engine's compiled kernels. Before it, a kernel first reached in another room (the room images of its walls)
    compiled in the callback on a fresh install, the callback stalled for seconds and the stream was lost
    (``bench vr --task speaker-following`` ran 0 callbacks)."""
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-c", WARM_CHECK], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    line = next(ln for ln in p.stdout.splitlines() if ln.startswith("ROOMS"))
    f = line.split()
    assert int(f[1]) >= 4 and int(f[3]) >= 1 and int(f[5]) >= 30, line  # the check covers something
    assert line.endswith("NEW []"), line


def test_a_live_window_without_the_stream_is_an_error_not_zero_xruns(private_jack):
    """``bench vr``'s live windows: a window that played under 90% of its frames while the server reported no late
    cycle is an error, and so is a stream lost during it, with the engine's news (it used to report 0 xruns over 0
    callbacks). A short window whose server was late is a measurement: the dummy driver skips the cycles it slept
    through, and the xruns count them."""
    from app.bench.vr import _check_stream

    srv = private_jack()
    eng = _engine()
    eng.start()
    try:
        assert eng.wait_callbacks(20) >= 20
        eng.mark()
        assert eng.wait_callbacks(10) >= 10
        assert _check_stream(eng, eng.telemetry(), 0.04) == 1920  # 10 blocks of 256 frames: over 90% of 0.04 s
        with pytest.raises(DeviceError, match=r"played \d+ of the window's 48000 frames \(engine running\) and "
                                              r"the audio server reported no late cycle"):
            _check_stream(eng, {**eng.telemetry(), "xrun_blocks": 0}, 1.0)
        # the server held off the CPU for 0.15 s mid-window (as a loaded machine does): its dummy driver wakes late,
        # skips the cycles it slept through and tells its clients, so the window is short of frames by the stall and
        # holds an xrun: a measurement, not an error
        import os
        import signal
        import time

        eng.mark()
        t0 = time.perf_counter()
        assert eng.wait_callbacks(10) >= 10
        os.kill(srv.proc.pid, signal.SIGSTOP)
        try:
            time.sleep(0.15)  # the stall itself (not a wait for anything)
        finally:
            os.kill(srv.proc.pid, signal.SIGCONT)
        assert eng.wait_callbacks(20) >= 20
        tel, window = eng.telemetry(), time.perf_counter() - t0
        assert tel["frames"] < 0.9 * window * 48000 and tel["xruns"] >= 1 and tel["xrun_blocks"] >= 1, (tel, window)
        _check_stream(eng, tel, window)
        srv.stop()
        raised = None
        for _ in range(400):  # the worker's supervisor notices within its stall limit
            try:
                _check_stream(eng, eng.telemetry(), 0.0)
            except DeviceError as exc:
                raised = str(exc)
                break
            eng.wait_callbacks(1, timeout=0.05)
        assert raised is not None and "is lost" in raised and "audio device lost" in raised, raised
    finally:
        eng.stop()


def test_a_live_window_whose_stream_stopped_calling_back_is_an_error(private_jack):
    """``bench vr``'s check after a window: a stream whose callback stopped while the engine still says "running"
    (its worker, the callback's and the supervisor's process, held off the CPU: nobody is left to report) is an
    error, not a window without xruns."""
    import os
    import signal

    from app.bench.vr import _check_stream

    private_jack()
    eng = _engine()
    eng.start()
    try:
        assert eng.wait_callbacks(20) >= 20
        tel = eng.telemetry()
        os.kill(eng._proc.pid, signal.SIGSTOP)
        try:
            with pytest.raises(DeviceError, match="stopped calling back at the window's end"):
                _check_stream(eng, tel, 0.0)
            assert eng.state == "running"  # the engine had no news: the check itself found it
        finally:
            os.kill(eng._proc.pid, signal.SIGCONT)
    finally:
        eng.stop()


def test_where_real_time_is_refused_each_thread_takes_the_highest_time_shared_priority(private_jack, monkeypatch):
    """Some machines refuse SCHED_FIFO even to root (the lent machines in README's "Benchmarks"): then the JACK
    server's threads and the callback run at nice -20, the supervisor at -15 and the robots at -10, and the news says
    so; the platform probe runs time-shared too. Where a nice value is refused as well, the news says that."""
    import os
    import threading

    from app.audio_rt import sched
    from app.audio_rt.loopback import PlatformProbe

    may = sched.nice_allowed(-20)  # root here; an unprivileged CI user may not
    # the server as such a machine runs it (jackd --no-realtime): no thread of it at a real-time priority
    srv = private_jack(realtime=False)
    assert "SCHED_FIFO" not in srv.scheduling and "time-shared nice " in srv.scheduling, srv.scheduling
    assert ("time-shared nice -20" in srv.scheduling) == may, srv.scheduling
    eng = _engine()
    eng.start()
    try:
        assert eng.wait_callbacks(20) >= 20
        cb = eng.telemetry()["callback_scheduling"]
        assert cb == f"time-shared (SCHED_OTHER, nice {-20 if may else 0})", cb
    finally:
        eng.stop()
    # a supervisor refused FIFO: nice -15, which this thread then has (checked from outside it)
    def refuse(*a):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(sched.os, "sched_setscheduler", refuse)
    got = {}

    def supervisor():
        got["news"] = sched.favour_this_thread(4, sched.NICE_SUPERVISOR, "supervisor")
        got["nice"] = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())

    t = threading.Thread(target=supervisor)
    t.start()
    t.join()
    if may:
        assert got == {"news": "time-shared, nice -15 (SCHED_FIFO refused: Operation not permitted)", "nice": -15}
    else:
        assert got["news"].endswith("; nice -15 refused)") and got["nice"] >= 0, got
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == 0  # the caller's own thread untouched
    # SONICVERSE_RT_NICE names the threads that take the fallback (an A/B on a lent machine): 'none', none
    monkeypatch.setenv("SONICVERSE_RT_NICE", "callback,server")
    t = threading.Thread(target=supervisor)
    t.start()
    t.join()
    assert got["news"].endswith("; no nice asked: SONICVERSE_RT_NICE)") and got["nice"] == 0, got
    assert sched.nice_roles() == {"callback", "server"}
    monkeypatch.setenv("SONICVERSE_RT_NICE", "none")
    assert sched.nice_roles() == frozenset()
    monkeypatch.setenv("SONICVERSE_RT_NICE", "callbak")
    with pytest.raises(ConfigError, match=r"unknown thread role\(s\) \['callbak'\]"):
        sched.nice_roles()
    monkeypatch.delenv("SONICVERSE_RT_NICE")
    assert not sched.fifo_allowed()
    # cyclictest cannot run there (it takes real time whatever its --policy): a pinned Python process per CPU sleeps
    # to the same 1 ms deadlines, at nice -20 where allowed; its rows go through the same attribution
    monkeypatch.setattr(sched, "fifo_allowed", lambda: False)
    probe = PlatformProbe(1.0, lead=0.5, tail=1.0)
    assert probe.due() > 0.3  # the processes start before the window opens...
    probe.wait_start()
    assert probe.due() <= 0
    res = probe.result()
    assert probe.span_s[0] == 0.0 and probe.span_s[1] >= 1.9  # ...and run a tail past its end: neither their
    # start-up nor their rows written at the end fall in the window (on a lent machine both cost an xrun)
    assert res["probe_scheduling"] == \
        f"time-shared, nice {-20 if may else 0} (SCHED_FIFO refused): a Python process per CPU", res
    assert "why" not in res and 0.9 * os.cpu_count() * 1000 <= res["wakeups"] <= os.cpu_count() * 1000, res
    assert len(res["wakeup_ms_max"]) == os.cpu_count() and all(0 <= m < 1000 for m in res["wakeup_ms_max"])
    assert 0 <= probe.samples[:, 0].min() and probe.samples[:, 0].max() < 1.0
    # sleeping to a deadline in Python is late by tens of microseconds, not by a stall, on most wake-ups
    assert np.median(probe.samples[:, 1]) < 0.5, np.percentile(probe.samples[:, 1], [50, 99, 100])


def test_cli_devices_and_loopback_test(jack, cli):
    r = cli("audio", "devices", "--json", check_rc=0)
    devs = json.loads(r.stdout)["devices"]
    assert any(d["name"] == "system" and d["outputs"] == 2 for d in devs)
    r = cli("audio", "loopback-test", "--seconds", "2", "--sources", "2", "--scene", SCENE, "--json", check_rc=0)
    res = json.loads(r.stdout)
    for k in ("round_trip_ms", "block_ms", "xruns", "callbacks", "callback_p99_ms"):
        assert k in res
    assert res["round_trip_ms"] <= 2 * res["block_ms"] + 1.0 and res["callbacks"] > 300
    r = cli("audio", "loopback-test", "--device", "nope", check_rc=2)
    assert r.stderr.count("\n") == 1 and "no output device 'nope'" in r.stderr
