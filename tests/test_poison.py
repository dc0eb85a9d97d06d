"""No input silences the audio: every entry point (file, sound bank, live block, microphone, API gain, cached
assets) is checked or sanitised where it enters, and a listener whose recursive states were poisoned anyway recovers
within a block and says so."""
import dataclasses
import json

import numpy as np
import pytest
import soundfile as sf

from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig
from sonicverse_core.errors import AssetError, ConfigError

SCENE = "shoebox:6x5x3"


@pytest.fixture(scope="module")
def reverberant():
    from sonicverse_core.acoustics.probes import BakeConfig, bake
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene(SCENE)
    return scene, bake(scene, [[3.0, 2.5, 1.5]], BakeConfig(rays=500))


def _renderer(reverberant, **kw):
    scene, probes = reverberant
    r = AcousticRenderer(scene, RenderConfig(block=256, **kw), probes=probes)
    return r


def _rms(x):
    return float(np.sqrt(np.mean(np.asarray(x, np.float64) ** 2)))


@pytest.mark.parametrize("reverb", ["fdn", "convolution"])
def test_poisoned_state_recovers_within_a_block_and_says_so(reverberant, reverb):
    r = _renderer(reverberant, reverb=reverb)
    r.add_source(np.random.default_rng(0).normal(size=48000).astype(np.float32) * 0.1, (1.5, 1.5, 1.5))
    r.add_listener((4.0, 3.0, 1.6))
    r.render(0.3)
    ls = r._state[0]
    if reverb == "fdn":
        ls.late.fdn.buf[3] = np.nan  # NaN inside the feedback loop: before, silence for the rest of the run
    else:
        ls.late.conv.fdl[:, 5] = np.nan
    ls.direct.hist[0, 0, -1] = np.inf
    first = r.render_block()[0]
    assert np.all(np.isfinite(first)) and r.stats["recoveries"] == 1
    after = r.render(0.5)[0]
    assert np.all(np.isfinite(after)) and np.abs(after).max() <= 1.0
    assert _rms(after[:, -4800:]) > 1e-3  # sound again, not digital silence
    assert r.stats["recoveries"] == 1  # recovered once, for good


def test_a_poisoned_long_partition_recovers_once_it_plays(reverberant):
    """A NaN in the tail's long partitions (the part after its first 2 L samples) reaches the output only when the
    period that multiplies it plays, one or two periods on: the renderer recovers then, once, and sounds again."""
    from sonicverse_core.acoustics.probes import Probe

    scene, _ = reverberant
    dims = np.array([6.0, 5.0, 3.0])  # a probe ringing for 1.2 s: 225 blocks, long partitions of 8
    probe = Probe(dims / 2, np.full(9, 1.2), np.full(9, 1.2), np.zeros(3), dims, ("PlasterRough",) * 6, 1.0)
    r = AcousticRenderer(scene, RenderConfig(block=256), probes=[probe])
    r.add_source(np.random.default_rng(0).normal(size=48000).astype(np.float32) * 0.1, (1.5, 1.5, 1.5))
    r.add_listener((4.0, 3.0, 1.6))
    r.render(0.3)
    long = r._state[0].late.conv.long
    assert long is not None and long.quiet == 0
    long.fdl[:, 5] = np.nan
    after = r.render(0.5)[0]
    assert np.all(np.isfinite(after)) and np.abs(after).max() <= 1.0
    assert r.stats["recoveries"] == 1
    assert np.all(np.isfinite(long.fdl)) and _rms(after[:, -4800:]) > 1e-3


def test_live_blocks_with_nan_or_inf_are_zeroed_and_counted(reverberant):
    r = _renderer(reverberant)
    mic = r.add_source(None, (2.0, 2.0, 1.5), live=True)
    r.add_listener((4.0, 3.0, 1.6))
    rng = np.random.default_rng(1)
    for k in range(40):
        blk = rng.normal(size=256).astype(np.float32) * 0.1
        if k == 5:
            blk[17] = np.nan
        if k == 6:
            blk[:] = np.inf
        mic.push(blk)
        y = r.render_block()[0]
        assert np.all(np.isfinite(y))
    assert r.stats["nonfinite_input"] == 2 and r.stats["recoveries"] == 0
    assert _rms(y) > 1e-4


def test_gains_that_would_overflow_are_refused(reverberant):
    r = _renderer(reverberant)
    s = r.add_source(np.ones(1000, np.float32), (1, 1, 1))
    for g in (1e300, np.inf, np.nan, -1.0):
        with pytest.raises(ConfigError):
            s.gain = g
    with pytest.raises(ConfigError):
        r.add_source(np.ones(1000, np.float32), (1, 1, 1), gain=1e300)


def test_a_sound_file_with_nan_is_refused_naming_the_file(tmp_path):
    from assets_manifest.soundbank import load_sound

    x = np.zeros((4800, 1), np.float32)
    x[100] = np.nan
    sf.write(tmp_path / "nan.wav", x, 48000, subtype="FLOAT")
    with pytest.raises(AssetError, match="nan.wav.*NaN"):
        load_sound(str(tmp_path / "nan.wav"))
    sf.write(tmp_path / "empty.wav", np.zeros((0, 1), np.float32), 48000, subtype="FLOAT")
    with pytest.raises(AssetError, match="no samples"):
        load_sound(str(tmp_path / "empty.wav"))


def test_the_microphone_path_in_the_callback_zeroes_nan_and_the_user_still_hears():
    """The stream callback (run here with arrays, as PortAudio calls it): a NaN microphone block is zeroed before it
    reaches the ring the robots follow and the renderer; telemetry counts it; the scene keeps sounding."""
    import sounddevice as sd

    from app.audio_rt import config as C
    from app.audio_rt.config import AudioConfig, AudioScene, SourceSpec
    from app.audio_rt.core import AudioCore, Shared
    from app.audio_rt.engine import AudioEngine
    from app.audio_rt.shared import SharedBlock

    B = 256
    eng = AudioEngine(AudioConfig(sidetone=1.0), AudioScene(SCENE, sources=[SourceSpec("sofa/0", (4.0, 3.0, 1.2), 0.5)],
                                                            head=(2.0, 2.5, 1.6, 0.0, 0.0)))
    eng.sh = Shared(eng.layout, SharedBlock(eng.layout.size, private=True).buf, eng.n_listeners)
    core = AudioCore(eng.cfg, eng.scene, eng.sh, eng.pose_layout, role="user")
    eng.sh.poses.write(eng.pose_layout.frame(0.0, (2.0, 2.5, 1.6, 0.0, 0.0), sources=[(4.0, 3.0, 1.2)], gains=[0.5],
                                             sidetone=1.0))  # the frame loop's pose, as set_poses hands it
    ind, outd = np.zeros((B, 1), np.float32), np.zeros((B, 2), np.float32)
    rng = np.random.default_rng(2)
    heard = []
    for k in range(200):
        ind[:, 0] = rng.normal(size=B) * 0.05
        if k in (20, 21):
            ind[k, 0] = np.nan if k == 20 else np.inf
        core.callback(ind, outd, B, None, sd.CallbackFlags(0))
        heard.append(outd.copy())
    tele = eng.telemetry()
    assert tele["mic_blocks_nonfinite"] == 2 and tele["callback_errors"] == 0
    y = np.concatenate(heard)
    assert np.all(np.isfinite(y)) and _rms(y[-4800:]) > 1e-4
    ring = eng.sh.mic.data[0, :200 * B]
    assert np.all(np.isfinite(ring))


def test_corrupt_bake_cache_is_baked_again(tmp_path, monkeypatch, caplog):
    from sonicverse_core.acoustics import probes as P
    from sonicverse_core.scene.spec import load_scene

    monkeypatch.setenv("SONICVERSE_CACHE", str(tmp_path))
    scene = load_scene(SCENE)
    pos = [[3.0, 2.5, 1.5]]
    cfg = P.BakeConfig(rays=300)
    good = P.bake(scene, pos, cfg)
    path = next((tmp_path / "bakes").glob("*.json"))
    for junk in ("{}", "[]", "[{\"position\": [1, 2]}]", json.dumps([{**good[0].to_json(), "rt60": [float("nan")] * 9}]),
                 "not json"):
        path.write_text(junk)
        again = P.bake(scene, pos, cfg)
        assert len(again) == 1 and np.allclose(again[0].rt60, good[0].rt60)
        assert "baked again" in caplog.text
        caplog.clear()


def test_a_fresh_bake_and_its_cached_copy_are_the_same_numbers(tmp_path, monkeypatch):
    """An evaluation must not depend on whether the bake cache was warm: a fresh bake returns what the cache will give
    back (its JSON rounds to 4 decimals), to the bit."""
    from sonicverse_core.acoustics import probes as P
    from sonicverse_core.scene.spec import load_scene

    monkeypatch.setenv("SONICVERSE_CACHE", str(tmp_path))
    scene = load_scene(SCENE)
    pos = [[3.0, 2.5, 1.5], [1.234567, 1.7654321, 1.5]]
    fresh = P.bake(scene, pos, P.BakeConfig(rays=300))
    read = P.bake(scene, pos, P.BakeConfig(rays=300))
    uncached = P.bake(scene, pos, P.BakeConfig(rays=300), cache=False)
    for a, b, c in zip(fresh, read, uncached):
        for k in ("position", "rt60", "edt", "box_lo", "box_hi"):
            assert np.array_equal(getattr(a, k), getattr(b, k)) and np.array_equal(getattr(a, k), getattr(c, k)), k
        assert (a.box_materials, a.enclosed, a.room) == (b.box_materials, b.enclosed, b.room)
    assert fresh[1].position[0] == 1.2346


def test_corrupt_hrtf_cache_is_rebuilt(tmp_path, monkeypatch, caplog):
    from assets_manifest import hrtf

    monkeypatch.setenv("SONICVERSE_CACHE", str(tmp_path))
    good = hrtf.kemar()
    cached = next(tmp_path.glob("kemar-*.npz"))
    bad = good.hrirs.copy()
    bad[5, 0, 10] = np.nan
    np.savez(cached, sample_rate=good.sample_rate, directions=good.directions, hrirs=bad)
    again = hrtf.kemar()
    assert np.isfinite(again.hrirs).all() and np.array_equal(again.hrirs, good.hrirs)
    assert "rebuilt" in caplog.text


def test_corrupt_speech_cache_is_made_again(tmp_path, monkeypatch):
    from assets_manifest import speech

    monkeypatch.setenv("SONICVERSE_CACHE", str(tmp_path))
    x, sr = speech.speak("bring me the cushion")
    wav = next((tmp_path / "speech").glob("*.wav"))
    y = sf.read(wav, dtype="float32")[0]
    y[100] = np.nan
    sf.write(wav, y, sf.info(wav).samplerate, subtype="FLOAT")
    x2, _ = speech.speak("bring me the cushion")
    assert np.isfinite(x2).all() and len(x2) == len(x)


def _sofa(path, directions_deg, radii=None):
    """A SimpleFreeFieldHRIR file from KEMAR measurements nearest the given (azimuth, elevation) pairs."""
    import sofar

    from assets_manifest.hrtf import kemar, sph_to_vec

    k = kemar()
    d = sph_to_vec(directions_deg[:, 0], directions_deg[:, 1])
    idx = np.argmax(d @ k.directions.T, axis=1)
    s = sofar.Sofa("SimpleFreeFieldHRIR")
    s.Data_IR = k.hrirs[idx].astype(np.float64)
    s.Data_SamplingRate = float(k.sample_rate)
    r = np.ones(len(d)) * 1.2 if radii is None else radii
    s.SourcePosition = np.c_[directions_deg, r]
    s.SourcePosition_Type = "spherical"
    s.SourcePosition_Units = "degree, degree, metre"
    sofar.write_sofa(str(path), s)
    return str(path)


@pytest.mark.parametrize("layout", ["horizontal", "sparse", "radii"])
def test_sofa_files_of_common_layouts_load_and_render(tmp_path, layout):
    az = np.arange(0, 360, 10.0)
    if layout == "horizontal":
        dirs = np.c_[az, np.zeros_like(az)]
        radii = None
    elif layout == "sparse":
        dirs = np.array([[0, 0], [90, 0], [180, 0], [270, 0], [0, 60], [0, -40]], float)
        radii = None
    else:
        ring = np.c_[az, np.zeros_like(az)]
        up = np.c_[az[::3], np.full(len(az[::3]), 40.0)]
        one = np.concatenate([ring, up])
        dirs = np.concatenate([one, one])
        radii = np.r_[np.full(len(one), 0.5), np.full(len(one), 1.5)]
    path = _sofa(tmp_path / f"{layout}.sofa", dirs, radii)
    r = AcousticRenderer(None, RenderConfig(hrtf=path))
    r.add_source(np.random.default_rng(0).normal(size=9600).astype(np.float32) * 0.1, (0.0, 2.0, 1.5))  # left
    r.add_listener((0.0, 0.0, 1.5), yaw=0.0)
    y = r.render(0.2)[0]
    assert np.all(np.isfinite(y))
    assert _rms(y[0]) > 1.5 * _rms(y[1])  # the source on the left is louder in the left ear


def test_sofa_files_that_cannot_work_are_refused(tmp_path):
    from assets_manifest.hrtf import load_sofa
    from sonicverse_core.acoustics.hrtf import HrtfInterpolator

    path = _sofa(tmp_path / "two.sofa", np.array([[90, 0], [270, 0]], float))
    with pytest.raises(AssetError, match="at least 3"):
        HrtfInterpolator(load_sofa(path), 48000, 128)
    (tmp_path / "junk.sofa").write_bytes(b"\x89HDF\r\n junk")
    with pytest.raises(AssetError, match="cannot read SOFA"):
        load_sofa(tmp_path / "junk.sofa")


def _steady_core(scene: str, n_sources: int):
    """An AudioCore (user with microphone, one robot, n scene sources, paths and coupled rooms in the apartment)
    and a function running k callbacks whose poses keep every position still while the head turns."""
    import sounddevice as sd

    from app.audio_rt.config import AudioConfig, AudioScene, SourceSpec
    from app.audio_rt.core import AudioCore, Shared
    from app.audio_rt.engine import AudioEngine
    from app.audio_rt.shared import SharedBlock

    B = 256
    spots = [(1.5, 1.5, 1.2), (5.0, 2.0, 1.0), (9.0, 2.0, 1.0), (8.0, 6.0, 1.2), (2.0, 7.0, 1.0), (6.0, 5.0, 1.0)]
    srcs = [SourceSpec("sofa/0" if i % 2 else "sink/1", spots[i % len(spots)], 0.3) for i in range(n_sources)]
    eng = AudioEngine(AudioConfig(), AudioScene(scene, sources=srcs, robots=[(5.0, 6.0, 0.4, 0.0)],
                                                head=(4.0, 5.0, 1.6, 0.0, 0.0)))
    eng.sh = Shared(eng.layout, SharedBlock(eng.layout.size, private=True).buf, eng.n_listeners)
    core = AudioCore(eng.cfg, eng.scene, eng.sh, eng.pose_layout, role="all")
    ind, outd = np.zeros((B, 1), np.float32), np.zeros((B, 2), np.float32)
    rng = np.random.default_rng(4)
    noise = (rng.normal(size=(64, B)) * 0.05).astype(np.float32)
    # the frame loop's pose frames (made on its side, before the count): still positions, the robot turning (the
    # user's head stays: turning it would move the mouth, a source, by more than the tolerance now and then)
    frames = [eng.pose_layout.frame(k * 2 * B / 48000, (4.0, 5.0, 1.6, 0.0, 0.0), robots=[(5.0, 6.0, 0.4, 1.5 * k)],
                                    sources=[s.position for s in srcs], gains=[0.3] * n_sources,
                                    doors=[1.0] * eng.pose_layout.n_doors) for k in range(1000)]
    flags = sd.CallbackFlags(0)

    def run(k0, n):
        for k in range(k0, k0 + n):
            if k % 2 == 0:  # a frame every other block (90 Hz frames, 187.5 Hz blocks)
                eng.sh.poses.write(frames[(k // 2) % len(frames)])
            ind[:, 0] = noise[k % len(noise)]
            core.callback(ind, outd, B, None, flags)

    return eng, core, run


def test_the_callback_allocates_no_array_memory_in_steady_state():
    """With every source and listener still (within the occlusion tolerance) and no door moving, while a robot's
    head turns and poses stream in: NumPy allocates no array memory in 1,000 callbacks (a counting data-memory handler);
    numba's allocations per block do not grow with the number of sources (its call boundary wraps each array
    argument in a small header: no kernel makes an array) and are all freed; tracemalloc sees no growth and only
    the interpreter's small objects within a block."""
    import tracemalloc

    from numba.core.runtime import _nrt_python, rtsys

    from allocs import counting

    per_block = {}
    was = _nrt_python.memsys_stats_enabled()
    _nrt_python.memsys_enable_stats()
    try:
        for n_sources in (2, 6):
            eng, core, run = _steady_core("builtin:apartment", n_sources)
            run(0, 200)  # warm-up: JIT, first rays and paths, plans, caches
            assert core.r.stats["paths"] > 0 and "coupled_rooms" in core.r.subsystems  # all of it is exercised
            s0 = rtsys.get_allocation_stats()
            with counting() as numpy_allocs:
                run(200, 1000)
                assert numpy_allocs() == 0, f"{numpy_allocs()} NumPy allocations in 1,000 callbacks"
            s1 = rtsys.get_allocation_stats()
            per_block[n_sources] = (s1.alloc - s0.alloc) / 1000
            assert s1.alloc - s0.alloc == s1.free - s0.free  # every header freed within its call
            tracemalloc.start()
            try:
                before = tracemalloc.get_traced_memory()[0]
                tracemalloc.reset_peak()
                run(1200, 500)
                after, peak = tracemalloc.get_traced_memory()
            finally:
                tracemalloc.stop()
            print(f"{n_sources} sources: numba {per_block[n_sources]:.1f} headers/block, tracemalloc growth "
                  f"{after - before} B, peak {peak - before} B")
            assert after - before < 4 * 1024, f"grew by {after - before} bytes over 500 callbacks"
            assert peak - before < 64 * 1024  # small objects only: one listener's (2, 256) float64 block is 4 kB
            assert eng.telemetry()["callback_errors"] == 0
    finally:
        if not was:
            _nrt_python.memsys_disable_stats()
    # a kernel making an array per source would add >= 4 per block here; which glue kernels run varies a little
    # from block to block (the pose ramp ends between frames), hence not exact equality
    assert abs(per_block[6] - per_block[2]) < 1, per_block


def test_bakes_cached_before_min_scattering_keep_their_keys():
    """``BakeConfig.min_scattering`` (bench fidelity's diffuse check) is left out of a bake's cache key at its
    default, 0: the bakes on disk from before it stay valid; any other value bakes apart."""
    import hashlib
    from dataclasses import asdict

    from sonicverse_core.acoustics import probes as P
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene(SCENE)
    pos = np.array([[3.0, 2.5, 1.5]])
    cfg = P.BakeConfig()
    h = hashlib.sha256()  # the key as it was made before the field
    h.update(scene.static_hash().encode())
    h.update(np.round(pos, 4).tobytes())
    h.update(json.dumps({k: v for k, v in asdict(cfg).items() if k != "min_scattering"}, sort_keys=True).encode())
    h.update(b"-")
    h.update(b"probes-v7")
    assert P._cache_key(scene, pos, cfg, [None]) == h.hexdigest()[:24]
    assert P._cache_key(scene, pos, P.BakeConfig(min_scattering=0.5), [None]) != h.hexdigest()[:24]
