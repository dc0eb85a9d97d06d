"""The renderer's parts and its stability: compiled kernels vs NumPy twins, early reflections vs image-source
theory, occlusion updates, leave-out rules, multiple listeners, extremes, long runs, CLI front end."""
import json
import tracemalloc

import numpy as np
import pytest

from sonicverse_core.acoustics.probes import SPEED_OF_SOUND, Probe
from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig
from sonicverse_core.scene.spec import load_scene

FS = 48000


def _probe(dims, rt=0.5, material="PlasterRough"):
    dims = np.asarray(dims, float)
    return Probe(dims / 2, np.full(9, rt), np.full(9, rt), np.zeros(3), dims, (material,) * 6, 1.0)


def _max_step(y):
    return float(np.max(np.abs(np.diff(y.astype(np.float64), axis=1))))


def test_gather_kernel_matches_numpy():
    from sonicverse_core.acoustics.kernels import gather

    rng = np.random.default_rng(0)
    H, B = 4096, 64
    ring = rng.normal(size=(3, H)).astype(np.float32)
    d_old = rng.uniform(0, 0.02, (3, 2))
    d_new = d_old + rng.uniform(-2e-4, 2e-4, (3, 2))  # moving sources
    d_new[2, 1] = 0.08  # a jump of thousands of samples within the block (a teleport)
    g_old, g_new = rng.uniform(0, 1, (3, 2)), rng.uniform(0, 1, (3, 2))
    out = np.empty((3, 2, B), np.float32)
    base = -B  # the write position wrapped: reads wrap around the ring
    gather(ring, base, d_old, d_new, float(FS), g_old, g_new, out, 0)
    t = np.arange(B)
    r = (t + 1) / B
    rows = np.arange(3)[:, None, None]

    def tap(d):
        pos = base + t - d * FS
        i0 = np.floor(pos).astype(int)
        fr = pos - i0
        return ring[rows, i0 % H] * (1 - fr) + ring[rows, (i0 + 1) % H] * fr

    swept = tap(d_old[..., None] + (d_new - d_old)[..., None] * r)  # motion: the delay sweeps (Doppler)
    jump = tap(d_old[..., None]) * (1 - r) + tap(d_new[..., None]) * r  # a teleport: crossfade
    teleport = (np.abs(d_new - d_old) * FS / B > 0.5)[..., None]
    ref = np.where(teleport, jump, swept) * (g_old[..., None] + (g_new - g_old)[..., None] * r)
    assert teleport.sum() >= 1 and (~teleport).sum() >= 4
    np.testing.assert_allclose(out, ref, atol=2e-5)


def test_gather_kernel_slow_motion_runs_match_numpy():
    """The common case (the delay moves by at most 8 samples across the block, no wrap) reads the ring in runs of
    one integer offset; every motion in it, either way, from a whole-sample start and across run ends, matches the
    interpolation formula as closely as float32 allows."""
    from sonicverse_core.acoustics.kernels import gather

    rng = np.random.default_rng(3)
    H, B = 8192, 256
    moves = np.array([0.0, 1e-9, -1e-9, 0.3, -0.3, 0.999, -0.999, 1.0, -1.0, 1.5, -2.25, 3.7, -5.0, 8.0, -8.0, 7.99])
    n = len(moves)
    ring = rng.normal(size=(n, H)).astype(np.float32)
    d_old = np.round(rng.uniform(100, 2000, (n, 1))) / FS  # whole samples: each run's fraction starts at 0
    d_old[::2] += rng.uniform(0, 1, (n // 2 + n % 2, 1)) / FS
    d_new = d_old + moves[:, None] / FS
    g_old, g_new = rng.uniform(0, 1, (n, 1)), rng.uniform(0, 1, (n, 1))
    out = np.full((n, 1, 37 + B), 7.0, np.float32)  # the taps fill each row's end (an overlap-save input)
    base = 4000
    gather(ring, base, d_old, d_new, float(FS), g_old, g_new, out, 37)
    t = np.arange(B)
    r = (t + 1) / B
    pos = base + t - (d_old + (d_new - d_old) * r) * FS  # (n, B)
    i0 = np.floor(pos).astype(int)
    fr = pos - i0
    rows = np.arange(n)[:, None]
    ref = (ring[rows, i0] * (1 - fr) + ring[rows, i0 + 1] * fr) * (g_old + (g_new - g_old) * r)
    np.testing.assert_allclose(out[:, 0, 37:], ref, atol=2e-6)
    assert np.all(out[:, 0, :37] == 7.0)


def test_barycentric_weights_reproduce_direction():
    from assets_manifest.hrtf import kemar
    from sonicverse_core.acoustics.hrtf import HrtfInterpolator

    h = HrtfInterpolator(kemar(), FS, taps=64)
    d = np.random.default_rng(1).normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    tri, w = h.weights(d)
    assert np.all(w >= 0) and np.allclose(w.sum(1), 1)
    v = np.einsum("mk,mkj->mj", w, h.directions[tri])  # the interpolation point lies on the ray of d
    cos = np.einsum("ij,ij->i", v / np.linalg.norm(v, axis=1, keepdims=True), d)
    assert cos.min() > 1 - 1e-9
    # a measured direction gets its own filter
    tri, w = h.weights(h.directions[:50])
    picked = tri[np.arange(50), np.argmax(w, 1)]
    np.testing.assert_array_equal(picked, np.arange(50))


def test_early_reflection_arrival_times_match_image_sources():
    dims = (6.0, 4.0, 3.0)
    src, lis = np.array([1.7, 1.3, 1.2]), np.array([4.1, 2.6, 1.6])
    r = AcousticRenderer(None, RenderConfig(output="mono", occlusion=False, late_reverb=False, near_field_gain=0),
                         probes=[_probe(dims)])
    imp = np.zeros(FS // 10, np.float32)
    imp[0] = 1.0
    r.add_source(imp, src, loop=False)
    r.add_listener(lis)
    assert "early_reflections" in r.subsystems
    y = r.render(0.1)[0][0].astype(np.float64)
    # image sources of the 6 walls (first order) + the direct path
    images = [src]
    for a in range(3):
        for wall in (0.0, dims[a]):
            im = src.copy()
            im[a] = 2 * wall - src[a]
            images.append(im)
    delays = np.sort([np.linalg.norm(im - lis) / SPEED_OF_SOUND * FS for im in images])
    energy = y ** 2
    found = []
    for d in delays:
        win = slice(int(d) - 3, int(d) + 4)
        k = int(d) - 3 + np.argmax(energy[win])
        found.append(k)
        # linear interpolation splits a tap over the two samples around the exact delay
        assert abs(k - d) <= 1.0, (k, d)
        g = 1 / (np.linalg.norm(images[0] - lis) if d == delays[0] else 1)
        assert np.sum(energy[int(d) - 1: int(d) + 3]) > 0.3 * (min(g, 1) / (d / FS * SPEED_OF_SOUND)) ** 2 * 0.5
    # nothing arrives before the direct sound (but the zero-phase air-absorption curve's pre-ringing, < -40 dB)
    assert np.max(np.abs(y[: int(delays[0]) - 2])) < 1e-2 * np.max(np.abs(y))


def test_occlusion_follows_a_closing_door_in_the_next_block():
    s = load_scene("builtin:apartment?seed=0")
    door = s.doors[0]
    yaw = np.radians(door.closed_yaw)
    along, normal = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
    centre = np.asarray(door.hinge, float)[:2] + along * door.width / 2  # the middle of the doorway
    src = np.r_[centre + 1.2 * normal, 1.0]  # through the doorway, 1.2 m on either side
    lis = np.r_[centre - 1.2 * normal, 1.0]
    r = AcousticRenderer(s, RenderConfig(output="mono", late_reverb=False, early_reflections=False))
    r.add_source(np.ones(FS, np.float32) * 0.1, src)
    r.add_listener(lis)
    s.set_door(door.name, 1.0)
    r.render_block()
    open_t = r._state[0].occ_target[0].copy()
    s.set_door(door.name, 0.0)
    r.render_block()  # the very next block sees the change
    closed_t = r._state[0].occ_target[0].copy()
    assert np.allclose(open_t, 1.0)  # open: a clear path
    assert closed_t[-1] < 0.1 and np.all(np.diff(closed_t) <= 1e-12)  # closed: the leaf, more at high bands
    y = r.render_block()[0]  # and the output follows, smoothed across blocks
    assert np.all(np.isfinite(y))


def test_leave_out_what_a_scene_does_not_need():
    box = load_scene("shoebox:5x4x3")
    r = AcousticRenderer(box, RenderConfig(output="stereo"), probes=[_probe((5, 4, 3))])
    assert "occlusion" not in r.subsystems  # convex room: nothing can lie between two points inside
    assert "hrtf" not in r.subsystems and r.hrtf is None
    assert {"early_reflections", "late_reverb"} <= set(r.subsystems)
    r = AcousticRenderer(box, RenderConfig(), probes=[])
    assert "late_reverb" not in r.subsystems and "early_reflections" not in r.subsystems
    apt = load_scene("builtin:apartment?seed=0")
    r = AcousticRenderer(apt, RenderConfig(output="mono", late_reverb=False, early_reflections=False))
    assert "occlusion" in r.subsystems
    living = next(x for x in apt.rooms if x.type == "living room")
    c = np.r_[living.footprint.mean(0), 1.2]
    r.add_source(np.ones(FS, np.float32) * 0.1, c + [0.3, 0, 0])
    r.add_listener(c)
    r.render_block()
    # a segment whose box meets no part's box casts no rays
    assert r.stats["occlusion_skipped"] + r.stats["occlusion_rays"] == 1


def test_subsystems_share_one_protocol_and_keep_typed_per_listener_state():
    """Every subsystem gives each listener a typed state (a misspelt field is an error), grows it with the
    sources, and says how far back it reads; the history ring covers the farthest reader; a renderer without a
    subsystem has no state for it."""
    from sonicverse_core.acoustics.state import ListenerState, PerSource

    box = load_scene("shoebox:5x4x3")
    r = AcousticRenderer(box, RenderConfig(), probes=[_probe((5, 4, 3))])
    assert [p.name for p in r.parts] == ["direct", "early", "late"]  # convex: no occlusion, no paths
    for i in range(9):  # past the first capacity (8): every state grows
        r.add_source(np.ones(FS, np.float32) * 0.01, (1.0 + 0.2 * i, 1.0, 1.5))
    r.add_listener((4.0, 3.0, 1.5))
    ls = r._state[0]
    assert isinstance(ls, ListenerState) and ls.occlusion is None and ls.paths is None
    for part, st in zip(r.parts, ls.parts):
        assert isinstance(st, PerSource) and getattr(ls, part.name) is st
        for name in ("state", "grow", "max_delay", "render", "reset"):
            assert callable(getattr(part, name))
        with pytest.raises(AttributeError):
            st.no_such_field = 1.0
    assert ls.direct.hist.shape[0] >= 9 and ls.early.delay.shape[0] >= 9 and ls.late.send.shape[0] >= 9
    assert r.hist >= max(p.max_delay() for p in r.parts) * FS
    assert r.late.max_delay() > r.direct.max_delay()  # the late send's pre-delay
    y = r.render(0.1)[0]
    assert np.all(np.isfinite(y)) and np.abs(y).max() > 0
    apt = load_scene("builtin:apartment?seed=0")
    r = AcousticRenderer(apt, RenderConfig(late_reverb=False, early_reflections=False))
    assert [p.name for p in r.parts] == ["occlusion", "paths", "direct"]
    r.add_listener((0, 0, 1.5))
    assert r._state[0].late is None and r._state[0].occlusion is r._state[0].parts[0]


def test_two_listeners_hear_the_scene_from_their_own_poses():
    r = AcousticRenderer(None, RenderConfig(occlusion=False, late_reverb=False))
    r.add_source(np.random.default_rng(0).normal(size=FS).astype(np.float32) * 0.1, (0, 2, 0))
    r.add_listener((0, 0, 0), 0.0)  # source on the left
    r.add_listener((0, 4, 0), 0.0)  # source on the right
    a, b = (y.astype(np.float64)[:, 4800:] for y in r.render(0.5))
    assert np.mean(a[0] ** 2) > 2 * np.mean(a[1] ** 2)
    assert np.mean(b[1] ** 2) > 2 * np.mean(b[0] ** 2)


@pytest.mark.parametrize("dims,rt", [((0.3, 0.3, 0.3), 1e-4), ((300.0, 300.0, 300.0), 1e4),
                                     ((0.3, 0.3, 0.3), 1e4), ((300.0, 300.0, 300.0), 1e-4)])
def test_extreme_rooms_and_decays_stay_finite_and_bounded(dims, rt):
    for reverb in ("fdn", "convolution"):
        r = AcousticRenderer(None, RenderConfig(occlusion=False, reverb=reverb), probes=[_probe(dims, rt)])
        r.add_source(np.ones(FS, np.float32), np.asarray(dims) * 0.3)
        r.add_source(np.ones(FS, np.float32), np.asarray(dims) * 0.5)  # at the listener
        r.add_listener(np.asarray(dims) * 0.5)
        y = r.render(0.3)[0]
        assert np.all(np.isfinite(y)) and np.max(np.abs(y)) <= 1.0


def test_ten_thousand_teleports_no_click_above_threshold():
    rng = np.random.default_rng(7)
    r = AcousticRenderer(None, RenderConfig(block=64, occlusion=False), probes=[_probe((8, 6, 3), 0.8)])
    t = np.arange(FS * 2) / FS
    tone = (0.3 * np.sin(2 * np.pi * 220 * t)).astype(np.float32)
    s = r.add_source(tone, (2, 0, 1))
    lis = r.add_listener((4, 3, 1.5))
    prev = None
    worst = 0.0
    for _ in range(10_000):
        s.position = rng.uniform([0.2, 0.2, 0.2], [7.8, 5.8, 2.8])
        r.set_listener(lis, rng.uniform([0.2, 0.2, 0.2], [7.8, 5.8, 2.8]), rng.uniform(-360, 360))
        y = r.render_block()[0]
        assert np.all(np.isfinite(y)) and np.max(np.abs(y)) <= 1.0
        if prev is not None:
            worst = max(worst, _max_step(np.concatenate([prev[:, -1:], y], 1)))
        prev = y
    # the tone itself moves by at most 0.3 * 2 pi 220 / 48000 = 0.009 per sample at 1 m; gains, delays and filters
    # ramp across blocks, so no step comes near a click (stated threshold: 0.25 full scale per sample)
    assert worst < 0.25, worst


@pytest.mark.parametrize("reverb", ["convolution", "fdn"])
def test_long_run_no_memory_growth_no_denormals(reverb):
    rng = np.random.default_rng(3)
    r = AcousticRenderer(load_scene("shoebox:6x5x3"), RenderConfig(reverb=reverb), probes=[_probe((6, 5, 3), 1.2)])
    burst = np.zeros(FS, np.float32)
    burst[:2000] = rng.normal(size=2000).astype(np.float32) * 0.3  # a burst, then a decaying tail into silence
    r.add_source(burst, (1.5, 1.5, 1.2), loop=False)
    r.add_listener((4, 3, 1.5))
    for _ in range(200):
        r.render_block()
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    for _ in range(60 * FS // 256):  # one minute of audio (the hour-long soak is the slow variant)
        y = r.render_block()[0]
    after = tracemalloc.get_traced_memory()[0]
    tracemalloc.stop()
    assert after - before < 200_000, after - before
    assert np.all(y == 0) or np.min(np.abs(y[y != 0])) >= 1e-30
    late = r._state[0].late
    state = (late.fdn.buf, late.fdn.zi) if reverb == "fdn" else (late.conv.fdl, late.conv._frame)
    if reverb == "convolution":  # the tail's long partitions (a 1.2 s tail spans 225 blocks)
        state += (late.conv.long.fdl, late.conv.long.frame, late.conv.long.col, late.conv.long.acc)
    for arr in state:
        tiny = np.finfo(arr.real.dtype).tiny
        nz = np.abs(arr[arr != 0])
        assert len(nz) == 0 or nz.min() >= tiny  # no subnormal numbers in the reverb's state


@pytest.mark.slow
def test_an_hour_of_audio_without_drift():
    r = AcousticRenderer(load_scene("shoebox:6x5x3"), RenderConfig(), probes=[_probe((6, 5, 3), 1.0)])
    t = np.arange(FS) / FS
    r.add_source((0.2 * np.sin(2 * np.pi * 440 * t)).astype(np.float32), (1.5, 1.5, 1.2))
    r.add_listener((4, 3, 1.5))
    levels = []
    for k in range(3600 * FS // 256):
        y = r.render_block()[0]
        if k % (60 * FS // 256) == 0:
            levels.append(float(np.sqrt(np.mean(y.astype(np.float64) ** 2))))
        assert np.max(np.abs(y)) <= 1.0
    levels = np.array(levels[1:])
    assert np.all(np.isfinite(levels)) and levels.max() / levels.min() < 1.05  # steady state, no drift


def test_cli_render_and_bake_json(cli, tmp_path):
    out = tmp_path / "r.wav"
    res = cli("render", "shoebox:6x4x3", "--sound", "sofa", "--source", "1.5,1.5,1.2", "--listener", "4,2.5,1.5,90",
              "--seconds", "0.5", "--out", str(out), "--json")
    assert res.returncode == 0, res.stderr
    d = json.loads(res.stdout)
    assert out.is_file() and d["sample_rate"] == 48000 and len(d["peak"]) == 2 and len(d["rms"]) == 2
    assert {"direct", "hrtf", "early_reflections", "late_reverb"} <= set(d["subsystems"])
    assert "occlusion" not in d["subsystems"]
    res = cli("bake", "shoebox:6x4x3", "--at", "3,2,1.5", "--rays", "500", "--json")
    assert res.returncode == 0, res.stderr
    probes = json.loads(res.stdout)["probes"]
    assert len(probes) == 1 and len(probes[0]["rt60"]) == 9
    res = cli("render", "shoebox:6x4x3", "--sound", "sofa", "--source", "nan,1,1", "--listener", "1,1,1",
              "--out", str(out))
    assert res.returncode == 2 and res.stderr.count("\n") == 1


def test_cli_bench_audio_reports_realtime_fraction(cli):
    res = cli("bench", "audio", "--sources", "4", "--seconds", "0.3", "--scene", "shoebox:6x4x3")
    assert res.returncode == 0, res.stderr
    d = json.loads(res.stdout)
    assert set(d["realtime_fraction"]) >= {"median", "p99"} and d["reference"]["realtime_fraction"]["median"] > 0
    res = cli("bench", "audio", "--sources", "8", "--seconds", "0.3", "--scene", "builtin:two-rooms?door=open")
    assert res.returncode == 0, res.stderr
    d = json.loads(res.stdout)  # the subsystems a scene of two rooms needs, and what they did per listener
    assert {"paths", "coupled_rooms"} <= set(d["subsystems"])
    # per room (the default): the listener's own room's tails with its doors open and shut, blended, and the
    # slowest mode's; the whole space: one tail
    assert 2 <= d["per_listener"]["room_reverbs_convolved"]["max"] <= 4
    # a listener walking at a VR user's pace recasts its segments more often than the bench's slow walk
    res = cli("bench", "audio", "--sources", "8", "--seconds", "0.3", "--scene", "builtin:two-rooms?door=open",
              "--walk", "1.2")
    assert res.returncode == 0, res.stderr
    walking = json.loads(res.stdout)
    assert (d["walk_m_per_s"], walking["walk_m_per_s"]) == (0.15, 1.2)
    assert sum(walking["occlusion"].values()) > 2 * sum(d["occlusion"].values()) > 0, (walking, d["occlusion"])
    res = cli("bench", "audio", "--sources", "8", "--seconds", "0.3", "--scene", "builtin:two-rooms?door=open",
              "--whole-space")
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["per_listener"]["room_reverbs_convolved"]["max"] == 1


def test_bench_audio_times_blocks_without_the_collector_and_restores_it(monkeypatch):
    """bench audio renders its timed blocks as the live audio workers do, with the garbage collector off (checked
    inside the render) and its kernels warmed before the first block, and leaves the collector as it found it."""
    import gc

    from app.bench.engine import bench_audio
    from sonicverse_core.acoustics.renderer import AcousticRenderer

    seen, warmed = [], []
    render, warm = AcousticRenderer.render_block, AcousticRenderer.warm_kernels

    def spy(self, *a, **k):
        seen.append(gc.isenabled())
        return render(self, *a, **k)

    def warm_spy(self):
        warmed.append(len(seen))
        return warm(self)

    monkeypatch.setattr(AcousticRenderer, "render_block", spy)
    monkeypatch.setattr(AcousticRenderer, "warm_kernels", warm_spy)
    assert gc.isenabled()
    d = bench_audio(2, 0.1, "shoebox:6x4x3", reference_blocks=1)
    assert gc.isenabled() and seen and not any(seen)
    assert d["garbage_collector"].startswith("frozen and off")
    assert warmed == [0] and d["kernels"].startswith("warmed")  # as the live workers: before the first block


def test_bench_audio_tells_a_stalled_block_from_a_costly_one(monkeypatch):
    """A block over its duration is counted, and counted as the thread held off the CPU when its CPU time is under
    half its wall time: the clocks are faked, one block stalled (2.5 blocks' wall, 0.2 on the CPU) and one costly
    (1.5 blocks' wall, all of it on the CPU), the rest a tenth of a block."""
    import time as real_time

    from app.bench import engine

    block_s = 256 / 48000
    calls = {"n": 0}

    class Clock:
        wall = cpu = 0.0

        @staticmethod
        def perf_counter():
            return Clock.wall

        @staticmethod
        def thread_time():
            return Clock.cpu

    render = engine._audio_scene

    def scene(*a, **k):
        r = render(*a, **k)
        real_render = r.render_block

        def render_block(*a2, **k2):
            out = real_render(*a2, **k2)
            calls["n"] += 1
            wall, on_cpu = {60: (2.5, 0.2), 70: (1.5, 1.5)}.get(calls["n"], (0.1, 0.1))
            Clock.wall += wall * block_s
            Clock.cpu += on_cpu * block_s
            return out

        real_warm = r.warm_kernels

        def warm_kernels():
            real_warm()
            calls["n"] = 0  # then 50 warm-up blocks, then the timed ones: calls 60 and 70 are timed

        r.render_block, r.warm_kernels = render_block, warm_kernels
        return r

    monkeypatch.setattr(engine, "_audio_scene", scene)
    monkeypatch.setattr(engine, "time", type("T", (), {"perf_counter": Clock.perf_counter,
                                                      "thread_time": Clock.thread_time}))
    d = engine.bench_audio(2, 0.5, "shoebox:6x4x3", reference_blocks=1)
    assert real_time.perf_counter() > 0  # the real clock is untouched outside the bench module
    assert d["blocks_over_real_time"] == {"count": 2, "thread_off_the_cpu": 1, "at": [9, 19]}  # after 50 warm-up
    assert d["realtime_fraction"]["max"] == pytest.approx(2.5, rel=1e-6)


def test_bench_audio_breakdown_accounts_for_every_subsystem_built():
    """``bench audio --breakdown``: one share per subsystem the scene built (a door's home: occlusion and paths
    too), each timed inside the block, so the shares and the rest add up to the mean block and the rest is not
    negative; without the flag, no breakdown."""
    from app.bench.engine import bench_audio

    d = bench_audio(4, 0.2, "builtin:apartment", reference_blocks=1, breakdown=True)
    shares = d["per_subsystem"]
    assert set(shares) == {"direct", "early", "late", "occlusion", "paths", "other", "mean_block"}
    parts = [v for k, v in shares.items() if k not in ("other", "mean_block")]
    assert all(v > 0 for v in parts) and shares["other"] >= 0
    assert sum(parts) + shares["other"] == pytest.approx(shares["mean_block"], abs=2e-3)
    mix = d["late_remix"]  # the listener walked 3 cm at 0.15 m/s: re-mixed at least twice, inside the late share
    assert mix["count"] >= 2 and mix["us_each"] > 0 and 0 < mix["share"] < shares["late"]
    assert "per_subsystem" not in bench_audio(2, 0.1, "shoebox:6x4x3", reference_blocks=1)
