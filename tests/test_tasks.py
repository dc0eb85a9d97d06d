"""Navigation tasks: the contract battery over every task, episodes, metrics, baselines, eval CLI, vector envs."""
import json
import math
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest

import sonicverse_core.tasks  # noqa: F401  (registers the ids)
from sonicverse_core.errors import ActionError, ConfigError
from sonicverse_core.tasks import ENV_IDS
from sonicverse_core.tasks.episodes import in_sight
from sonicverse_core.tasks.episodes import GOAL_RADIUS, SUCCESS_RADIUS, homes
from sonicverse_core.tasks.metrics import mean_ci95, rate_ci95, shortest_actions, sna, spl

HOME = ("builtin:apartment?seed=6000",)


def _make(task, **kw):
    kw.setdefault("scenes", HOME)
    return gym.make(ENV_IDS[task], **kw)


def _rollout(env, seed, n=100):
    obs, info = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    out = [obs]
    for _ in range(n):
        a = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
        a[:2] = 0.05 * a[:2] + 0.95  # straight ahead: it will meet a wall
        if len(a) == 3:
            a[2] = -1.0
        obs, r, term, trunc, info = env.step(a)
        out.append(obs)
        if term or trunc:
            break
    return out


@pytest.mark.parametrize("task", list(ENV_IDS))
def test_contract_battery(task):
    from gymnasium.utils.env_checker import check_env

    env = _make(task)
    try:
        check_env(env.unwrapped, skip_render_check=True)
        a = _rollout(env, 11)
        b = _rollout(env, 11)
        assert len(a) == len(b)
        for oa, ob in zip(a, b):  # same seed -> same rollout, bit for bit
            for k in oa:
                assert np.array_equal(oa[k], ob[k]), k
        for prev, cur in zip(a, a[1:]):  # observations never share memory between steps
            for k in cur:
                assert not np.shares_memory(prev[k], cur[k]), k
        for k in a[0]:  # no observation is constant over a rollout
            assert any(not np.array_equal(a[0][k], o[k]) for o in a[1:]), f"{k} never changed"
        for o in a:
            assert env.observation_space.contains(o)
            assert np.all(np.isfinite(o.get("audio", 0))) and np.abs(o.get("audio", 0)).max() <= 1.0
        with pytest.raises(ActionError):
            env.step(np.full(env.action_space.shape, np.nan, np.float32))
        ep11 = env.unwrapped.episode
        _rollout(env, 12, n=2)
        assert env.unwrapped.episode.start != ep11.start  # another seed, another episode
    finally:
        env.close()


def test_default_sensors_per_task():
    assert {"pointgoal"} <= set(_make("AudioPointGoal").observation_space.spaces)
    assert "rgb" not in _make("AudioGoal").observation_space.spaces
    sem = _make("SemanticAudioNav")
    assert {"rgb", "depth", "spectrogram"} <= set(sem.observation_space.spaces)
    assert sem.action_space.shape == (3,)
    spec = sem.observation_space["spectrogram"].shape
    assert spec == (2, 64, 49)  # STFT 512/160/400 over 1 s at 16 kHz, pooled 4 x 2


def test_episodes_follow_the_paper():
    env = _make("AudioGoal").unwrapped
    from assets_manifest.soundbank import HEARD

    for seed in range(6):
        env.reset(seed=seed)
        ep = env.episode
        w = env.home.world
        goals = np.array(ep.goals)
        assert 1 <= len(goals) <= 9 and len({tuple(g) for g in goals}) == len(goals)
        assert in_sight(w.scene, w.scene.object(ep.object_name), goals).all()  # no wall hides the object
        obj = w.scene.object(ep.object_name)
        assert obj.category == ep.category
        lo, hi = obj.world_bounds()[:, :2]
        d = np.linalg.norm(np.maximum(np.maximum(lo - goals, goals - hi), 0), axis=1)
        assert np.all(d <= GOAL_RADIUS + 1e-9)
        assert np.all(w.grid.is_navigable(goals))  # reachable: the main component
        assert 1.0 <= ep.geodesic <= 10.0
        assert np.isfinite(w.grid.geodesic_distance(ep.start[:2], goals[0]))
        assert int(ep.sound.split("/")[1]) in HEARD and ep.sound.startswith(ep.category)
        assert env.task.geo0 == pytest.approx(ep.geodesic, abs=1e-9)
    unheard = _make("AudioGoal", sounds="unheard").unwrapped
    unheard.reset(seed=0)
    assert unheard.episode.sound.endswith("/3")
    # homes of the splits never overlap
    assert not set(homes("train", 50)) & set(homes("test", 50))


def test_a_terminal_position_behind_a_wall_is_dropped():
    """A shelf in validation home 1 (SemanticAudioNav's episode 1 there): of the positions within 1 m of its
    footprint, one lies behind a wall, in the next room. in_sight drops it and keeps those that see the shelf, and
    the episode no longer has it: the oracle used to stop there, out of sight of the shelf, and succeed."""
    from sonicverse_core.tasks import make_env
    from sonicverse_core.tasks.episodes import GOAL_RADIUS

    env = make_env("SemanticAudioNav", split="val", sensors=("pose",))
    env.reset(seed=1)
    w, ep = env.unwrapped.home.world, env.unwrapped.episode
    shelf = w.scene.object(ep.object_name)
    assert shelf.category == "shelf"
    lo, hi = shelf.world_bounds()
    seen, behind = np.array([[6.48, 10.42], [6.38, 10.02], [6.18, 8.32], [7.08, 8.48]]), np.array([[5.28, 8.62]])
    for p in (seen, behind):  # all within reach of the footprint, and on the floor
        assert np.all(np.linalg.norm(np.maximum(np.maximum(lo[:2] - p, p - hi[:2]), 0), axis=1) <= GOAL_RADIUS)
        assert np.all(w.grid.is_navigable(p))
    assert in_sight(w.scene, shelf, seen).all() and not in_sight(w.scene, shelf, behind).any()
    goals = np.array(ep.goals)
    assert len(goals) and np.linalg.norm(goals - behind, axis=1).min() > SUCCESS_RADIUS
    env.close()


def test_sound_stops_after_its_duration():
    env = _make("AudioGoal", everlasting=False, sound_seconds=(0.3, 0.3), reverb=False, sensors=("audio",)).unwrapped
    env.reset(seed=3)
    loud = []
    for _ in range(12):
        obs, *_ = env.step(np.zeros(2, np.float32))
        loud.append(float(np.abs(obs["audio"]).max()))
    assert max(loud[:2]) > 0 and max(loud[5:]) == 0.0  # heard, then silence (no reverb tail in this setting)


def test_audiogoal_sound_plays_all_episode_and_semantic_nav_sound_stops():
    """AudioGoal's sound is SoundSpaces' everlasting one: still heard after the longest duration SemanticAudioNav
    draws (20 s), as loud as at the start; with everlasting=False (SemanticAudioNav's default) the same episode falls
    silent."""
    def energies(task, **kw):
        env = _make(task, reverb=False, sensors=("audio",), **kw).unwrapped
        env.reset(seed=3)
        e = []
        for _ in range(230):  # 23 s standing still
            obs, *_ = env.step(np.zeros(env.action_space.shape, np.float32))
            e.append(float(np.mean(obs["audio"].astype(np.float64) ** 2)))
        env.close()
        return np.array(e), env.episode

    e, ep = energies("AudioGoal")
    assert math.isinf(ep.sound_seconds)
    first, last = e[:50].mean(), e[-30:].mean()  # the looped sound's mean power over 5 s and 3 s
    assert first > 0 and 10 * math.log10(last / first) > -6.0
    e2, ep2 = energies("AudioGoal", everlasting=False)
    assert ep2.goals == ep.goals and ep2.start == ep.start and 4.0 <= ep2.sound_seconds <= 20.0
    assert e2[-30:].max() == 0.0
    with pytest.raises(ConfigError, match="everlasting=False"):
        _make("AudioGoal", sound_seconds=(1.0, 2.0))
    with pytest.raises(ConfigError, match="everlasting must be"):
        _make("AudioGoal", everlasting="no")
    with pytest.raises(ConfigError, match="no goal sound"):
        _make("SpeakerFollowing", everlasting=True)
    assert not _make("SemanticAudioNav", sensors=("pose",)).unwrapped.task.everlasting


def test_reward_and_success_definitions():
    env = _make("AudioGoal", sensors=("pose",)).unwrapped
    env.reset(seed=4)
    d0 = env.task.prev_geo
    obs, r, term, trunc, info = env.step(np.array([0.0, 0.0], np.float32))
    assert r == pytest.approx(-0.01)  # no progress, no collision: the time penalty
    # teleport next to a goal and take one step: success, +10, episode over, metrics reported
    g = np.array(env.episode.goals[0])
    env.home.world.place_robot(*g, 0.0)
    obs, r, term, trunc, info = env.step(np.array([0.0, 0.0], np.float32))
    assert term and info["success"] and r == pytest.approx(d0 - info["distance_to_goal"] + 10 - 0.01, abs=1e-6)
    m = info["metrics"]
    assert m["success"] == 1.0 and m["sna"] > 0
    # semantic task: only a stop within 0.36 m succeeds
    sem = _make("SemanticAudioNav", sensors=("pose",)).unwrapped
    sem.reset(seed=4)
    obs, r, term, trunc, info = sem.step(np.array([0, 0, 1], np.float32))
    assert term and not info["success"]
    sem.reset(seed=4)
    sem.home.world.place_robot(*np.array(sem.episode.goals[0]), 0.0)
    _, _, term, _, info = sem.step(np.array([0, 0, -1], np.float32))
    assert not term and sem.privileged()["at_goal"]
    _, _, term, _, info = sem.step(np.array([0, 0, 1], np.float32))
    assert term and info["success"]


def test_metrics():
    assert spl(True, 5.0, 10.0) == 0.5 and spl(False, 5.0, 5.0) == 0.0 and spl(True, 5.0, 4.0) == 1.0
    assert sna(True, 50, 200) == 0.25 and sna(False, 50, 50) == 0.0
    assert shortest_actions(7.0, 0.7, 0.1) == 100
    ci = mean_ci95([1.0, 2.0, 3.0, 4.0])  # t(0.975, 3) = 3.182, s = 1.291, n = 4
    assert ci["mean"] == 2.5 and np.allclose(ci["ci95"], [2.5 - 2.0540, 2.5 + 2.0540], atol=1e-3)
    # Wilson: 2 of 30 gives [0.0185, 0.2132] (a t-interval gave +-0.000 for 0 of 30 and misplaced 2 of 30)
    w = rate_ci95([1, 1] + [0] * 28)
    assert np.allclose(w["ci95"], [0.01848, 0.21323], atol=1e-4) and w["mean"] == 2 / 30
    z = rate_ci95([0] * 30)
    assert z["ci95"][0] == 0.0 and np.isclose(z["ci95"][1], 0.11351, atol=1e-4)
    assert rate_ci95([1] * 30)["ci95"][1] == 1.0  # exactly, not 0.9999999999999999
    assert SUCCESS_RADIUS == 0.36


def test_oracle_proves_the_metrics_and_random_does_not():
    from app.tasks.evaluate import run_eval

    o = run_eval("AudioGoal", "oracle", 4, split="test", seed=1, env_kwargs={"scenes": HOME, "sensors": ("pose",)})
    assert o["sr"]["mean"] == 1.0 and o["spl"]["mean"] >= 0.95
    s = run_eval("SemanticAudioNav", "oracle", 3, split="test", seed=1,
                 env_kwargs={"scenes": HOME, "sensors": ("pose",)})
    assert s["sr"]["mean"] == 1.0
    r = run_eval("AudioGoal", "random", 3, split="test", seed=1,
                 env_kwargs={"scenes": HOME, "sensors": ("pose",), "max_steps": 150})
    assert r["spl"]["mean"] < o["spl"]["mean"]


def test_random_renders_nothing_it_does_not_read_and_scores_the_same():
    """`random` asks for the pose alone (no camera, no spectrogram, no ears rendered): the same seeds give the same
    drive, step for step, as in the env with the task's default sensors."""
    from agents import make_agent
    from sonicverse_core.tasks import make_env

    assert make_agent("random", np.random.default_rng(0), "SpeakerFollowing").env_kwargs() == {"sensors": ("pose",)}
    runs = []
    for sensors in (None, ("pose",)):
        env = make_env("AudioGoal", split="test", scenes=HOME, sensors=sensors, max_steps=40)
        obs, info = env.reset(seed=5)
        ag = make_agent("random", np.random.default_rng(5), "AudioGoal")
        ag.reset(env, obs, info)
        poses, done = [], False
        while not done:
            obs, _, term, trunc, info = env.step(ag.act(obs, info))
            poses.append(env.unwrapped.home.world.pose.copy())
            done = term or trunc
        assert ("depth" in obs) == (sensors is None) and ("spectrogram" in obs) == (sensors is None)
        blocks = env.unwrapped.renderer.blocks  # the ears: rendered every step, or not at all
        assert (blocks >= 40 * env.unwrapped.sub_blocks) if sensors is None else blocks == 0, blocks
        runs.append((np.array(poses), info["collisions"], info["path_length"]))
        env.close()
    assert len(runs[0][0]) == 40 and np.array_equal(runs[0][0], runs[1][0]) and runs[0][1:] == runs[1][1:]


def test_gan_itd_agent_localises_the_sound():
    """The binaural cue the gan-itd agent relies on: its ITD estimate puts a source on the correct side."""
    from agents.scripted import GanItdAgent as GanAgent

    env = _make("AudioGoal", sensors=("audio", "depth", "pose", "bump"), reverb=False).unwrapped
    obs, info = env.reset(seed=2)
    ag = GanAgent(np.random.default_rng(0))
    ag.reset(env, obs, info)
    src = env.source.position[:2]
    w = env.home.world
    bearing = np.degrees(np.arctan2(*(src - w.pose[:2])[::-1]))
    votes = []
    for yaw_off in (90.0, -90.0):  # source straight to the left, then to the right
        w.place_robot(*w.pose[:2], bearing - yaw_off)
        lat = []
        for _ in range(4):
            obs, *_ = env.step(np.zeros(2, np.float32))
            itd, e = ag._itd(obs["audio"])
            if e > 0:
                lat.append(itd)
        votes.append(np.median(lat))
    assert votes[0] > 1e-4 and votes[1] < -1e-4  # left ear leads for a source on the left


def test_sim_to_real_options():
    env = _make("AudioGoal", ego_noise=0.01, depth_min=0.8, depth_max=3.5, pose_noise=(0.01, 0.5),
                source_gain=(0.5, 2.0)).unwrapped
    obs, _ = env.reset(seed=5)
    d = obs["depth"]
    assert np.all((d == 0) | ((d >= 0.8) & (d <= 3.5)))
    quiet = _make("AudioGoal", ego_noise=0.01, everlasting=False, sound_seconds=(0.1, 0.1), reverb=False).unwrapped
    quiet.reset(seed=5)
    for _ in range(5):
        obs, *_ = quiet.step(np.zeros(2, np.float32))
    assert np.abs(obs["audio"]).max() == 0.0  # standing still: no motor noise, and the sound has stopped
    obs, *_ = quiet.step(np.ones(2, np.float32))
    rms = float(np.sqrt(np.mean(obs["audio"] ** 2)))
    assert rms == pytest.approx(0.01, rel=0.3)  # driving at top speed: ego-noise at the configured level
    env.reset(seed=6)
    p0 = env.home.world.pose.copy()
    for _ in range(10):
        obs, *_ = env.step(np.zeros(2, np.float32))
    assert np.allclose(env.home.world.pose, p0)
    assert np.linalg.norm(obs["pose"][:2]) > 0  # the odometry drifted while the robot stood still
    g = _make("AudioGoal", source_gain=(0.5, 2.0), sensors=("pose",)).unwrapped
    gs = []
    for s in range(4):
        g.reset(seed=s)
        gs.append(g.episode.source_gain)
    assert all(0.5 <= x <= 2.0 for x in gs) and len(set(gs)) == 4


def test_camera_is_loaded_only_when_asked_for():
    code = ("import sys, numpy as np, gymnasium as gym, sonicverse_core.tasks as t;"
            "e = gym.make(t.ENV_IDS['AudioGoal'], scenes=('builtin:apartment?seed=6000',), "
            "sensors=('audio', 'spectrogram', 'pose'));"
            "e.reset(seed=0); e.step(np.zeros(2, np.float32));"
            "print('pyrender' in sys.modules, 'OpenGL' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["False", "False"]


def test_vector_env_workers_render_in_their_own_context():
    from sonicverse_core.tasks import make_vector_env

    envs = make_vector_env("AudioGoal", 2, scenes=HOME, sensors=("rgb", "depth", "audio", "pose"), width=32,
                           height=32)
    try:
        obs, info = envs.reset(seed=[1, 2])
        assert obs["depth"].shape == (2, 32, 32, 1) and obs["rgb"].shape == (2, 32, 32, 3)
        for _ in range(3):
            obs, r, term, trunc, info = envs.step(np.tile([[0.5, 0.5]], (2, 1)).astype(np.float32))
        assert np.all(np.isfinite(r)) and obs["audio"].shape[:2] == (2, 2)
        assert np.any(obs["depth"] > 0)
    finally:
        envs.close()


def test_eval_cli_prints_metrics_and_writes_files(tmp_path, cli):
    r = cli("eval", "--task", "AudioGoal", "--agent", "oracle", "--episodes", "2", "--homes", "1", "--seed", "3",
            "--csv", str(tmp_path / "ep.csv"), "--maps", str(tmp_path / "maps"), "--json", check_rc=0)
    res = json.loads(r.stdout)
    for k in ("sr", "spl", "sna"):
        assert set(res[k]) >= {"mean", "ci95"}
    assert res["sr"]["mean"] == 1.0
    rows = (tmp_path / "ep.csv").read_text().strip().splitlines()
    assert len(rows) == 3 and rows[0].startswith("episode,")
    assert len(list((tmp_path / "maps").glob("*.png"))) == 2
    bad = cli("eval", "--task", "AudioGoal", "--agent", "oracle", "--episodes", "0")
    assert bad.returncode == 2 and bad.stderr.startswith("sonicverse: error:")


def test_eval_video_writes_frames_and_audio(tmp_path):
    import soundfile as sf

    from app.tasks.evaluate import run_eval

    run_eval("AudioGoal", "oracle", 1, seed=2, video=tmp_path, env_kwargs={"scenes": HOME, "width": 32,
                                                                         "height": 32})
    ep = tmp_path / "episode_0000"
    frames = sorted(ep.glob("frame_*.png"))
    audio, sr = sf.read(ep / "audio.wav")
    assert frames and sr == 16000 and audio.shape == (len(frames) * 1600, 2)
    # an agent that reads no audio (random: the pose alone) still gets what the robot heard on the video
    run_eval("AudioGoal", "random", 1, seed=2, video=tmp_path / "r", env_kwargs={"scenes": HOME, "width": 32,
                                                                               "height": 32, "max_steps": 20})
    audio, sr = sf.read(tmp_path / "r" / "episode_0000" / "audio.wav")
    assert audio.shape == (20 * 1600, 2) and np.sqrt(np.mean(audio ** 2)) > 1e-4


def test_bench_env_reports_steps_per_second(cli):
    r = cli("bench", "env", "--steps", "40", "--workers", "0", check_rc=0)
    b = json.loads(r.stdout)
    assert b["steps_per_s"] > 0 and b["reference_depth_renders_per_s"] > 0
    assert set(b["breakdown_ms"]) >= {"physics_ms", "audio_render_ms", "spectrogram_ms", "depth_render_ms",
                                      "audio_render_carrying_ms"}


def test_spectrogram_frames_match_the_librosa_definition_and_the_stream_equals_the_full_stft():
    """Periodic Hann 400 / hop 160 / FFT 512 magnitudes, frame for frame, against torch.stft (librosa's definition,
    center=False on the same window); the streaming spectrogram equals the full one block after block."""
    import torch

    from sonicverse_core.sensors.audio import HOP, N_FFT, WIN, Spectrogram, StreamingSpectrogram

    rng = np.random.default_rng(3)
    n = 16000
    x = rng.normal(size=(2, n)).astype(np.float32) * 0.1
    full = Spectrogram(n, pool=(1, 1))
    ours = np.expm1(full(x).astype(np.float64))  # (2, F, T) magnitudes, Nyquist bin dropped
    # torch (like librosa) frames n_fft samples with the window centred in them, (512 - 400) / 2 = 56 on each side
    start, pad = (n - WIN) % HOP, (N_FFT - WIN) // 2
    xp = np.pad(x[:, start:].astype(np.float64), ((0, 0), (pad, pad)))
    ref = torch.stft(torch.from_numpy(xp), N_FFT, HOP, WIN,
                     window=torch.hann_window(WIN, periodic=True, dtype=torch.float64), center=False,
                     return_complex=True).abs().numpy()[:, :-1, :]  # (2, 256, frames): Nyquist dropped as ours
    assert ours.shape == ref.shape
    np.testing.assert_allclose(ours, ref, rtol=2e-4, atol=2e-5)

    stream = StreamingSpectrogram(n, pool=(4, 2))
    pooled = Spectrogram(n, pool=(4, 2))
    y = rng.normal(size=(2, 5 * n)).astype(np.float32) * 0.1
    for k in range(0, 5 * n, 1600):  # 0.1 s steps at 16 kHz
        got = stream.push(y[:, k:k + 1600])
        if k + 1600 >= n:
            np.testing.assert_allclose(got, pooled(y[:, k + 1600 - n:k + 1600]), rtol=1e-5, atol=1e-6)
