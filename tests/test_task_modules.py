"""Task modules: the registry, the privileged channel, the person, speaker following, orientation training, the
`task` command."""
import json
import math
from pathlib import Path

import numpy as np
import pytest

import sonicverse_core.tasks as T
from sonicverse_core.errors import ConfigError
from sonicverse_core.tasks.registry import TASKS, task_spec

HOME = ("builtin:apartment?seed=6000",)


# --- registry ---------------------------------------------------------------------------------------------------
def test_every_task_is_listed_once_and_everything_reads_the_registry():
    import gymnasium as gym

    from agents import IMPLEMENTATIONS, make_agent
    from app.tasks.evaluate import TASK_NAMES

    clis = [s.cli for s in TASKS.values()]
    ids = [s.env_id for s in TASKS.values() if s.env_id]
    assert len(set(clis)) == len(clis) and len(set(ids)) == len(ids)
    assert set(T.ENV_IDS.values()) == set(ids)
    for s in TASKS.values():
        assert task_spec(s.cli) is task_spec(s.name) is s
        if s.env_id:
            assert s.env_id in gym.registry and gym.registry[s.env_id].max_episode_steps == s.max_steps
            for a in s.agents:  # every agent the registry names exists for the task
                assert make_agent(a, np.random.default_rng(0), s.name) is not None
                assert a in IMPLEMENTATIONS[s.name]
        assert s.metrics and set(s.rates) <= set(s.metrics)
    assert set(TASK_NAMES) == {"AudioGoal", "AudioPointGoal", "SemanticAudioNav"}
    with pytest.raises(ConfigError, match="unknown task"):
        task_spec("voice-teleport")
    with pytest.raises(ConfigError, match="unknown agent 'gan' for speaker-following"):
        make_agent("gan", None, "speaker-following")
    with pytest.raises(ConfigError, match="no robot env"):
        T.make_env("orientation-training")
    with pytest.raises(ConfigError, match="no option"):
        T.make_env("AudioGoal", person_speed=3)


class _Blind:
    """An env seen through the Gymnasium interface only: privileged() fails the test."""

    def __init__(self, env):
        self._env = env

    def privileged(self):
        raise AssertionError("a sensor-only agent read privileged state")

    def __getattr__(self, k):
        return getattr(self._env, k)


@pytest.mark.parametrize("task,agent", [("SpeakerFollowing", "scripted"), ("AudioGoal", "gan"),
                                        ("SemanticAudioNav", "gan"), ("SpeakerFollowing", "random")])
def test_sensor_agents_never_read_privileged_state(task, agent):
    from agents import make_agent

    env = T.make_env(task, scenes=HOME, max_steps=40)
    obs, info = env.reset(seed=1)
    ag = make_agent(agent, np.random.default_rng(0), task)
    blind = _Blind(env)
    ag.reset(blind, obs, info)
    for _ in range(40):
        obs, r, term, trunc, info = env.step(ag.act(obs, info))
        if term or trunc:
            break
    env.close()


# --- the person -------------------------------------------------------------------------------------------------
def _world():
    from sonicverse_core.scene.spec import load_scene
    from sonicverse_core.world import World

    return World(load_scene(HOME[0]))


def test_person_walks_navigable_paths_at_its_speed_pauses_and_stops():
    from sonicverse_core.world.person import Person, PersonConfig

    w = _world()
    rng = np.random.default_rng(3)
    route = w.grid.sample(rng, 3)
    p = Person(w, route, PersonConfig(pause_s=(1.0, 1.0), turn_deg_s=1e6), speed=1.2)
    pos, moving = [p.pos.copy()], []
    while not p.finished and p.t < 120:
        p.advance(0.1)
        pos.append(p.pos.copy())
        moving.append(p.walking)
    pos = np.array(pos)
    assert p.finished and np.allclose(p.pos, route[-1], atol=1e-6)
    assert np.all(w.grid.is_navigable(pos))  # on the floor the whole way (through doors)
    steps = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    assert steps.max() <= 1.2 * 0.1 + 1e-9  # never faster than its walking speed
    assert p.walked == pytest.approx(p.length, rel=1e-6)
    # walking time = length / speed, plus the pause at the middle place
    assert p.stop_time == pytest.approx(p.length / 1.2 + 1.0, abs=0.25)
    assert abs(p.mouth[2] - (w.base.z_floor + 1.58)) < 1e-9


def test_a_guide_keeps_a_robots_pace_and_waits_only_outside_the_band():
    """A robot close behind: the person's own speed; more than pace_gap behind: pace_speed; more than escort_gap
    behind (past the band's 2.5 m): they stand until it is within escort_resume, at most max_wait_s."""
    from sonicverse_core.tasks.following import BAND
    from sonicverse_core.world.person import Person, PersonConfig

    w = _world()
    rng = np.random.default_rng(3)
    route = w.grid.sample(rng, 2)
    cfg = PersonConfig(turn_deg_s=1e6)
    assert cfg.escort_gap > BAND[1] and cfg.pace_speed < w.robot.max_speed
    p = Person(w, route, cfg, speed=1.2)

    def step(gap):
        before = p.walked
        p.advance(0.1, robot_gap=gap)
        return (p.walked - before) / 0.1

    p.advance(0.3)  # past the first turn
    assert step(1.0) == pytest.approx(1.2)
    assert step(cfg.pace_gap + 0.1) == pytest.approx(cfg.pace_speed)
    assert step(cfg.escort_gap + 0.1) == 0.0 and p.escorting
    assert step(2.2) == 0.0  # waiting goes on until the robot is back within escort_resume
    assert step(cfg.escort_resume - 0.1) == pytest.approx(cfg.pace_speed) and not p.escorting  # walks on, slowly
    waited = 0
    while step(10.0) == 0.0:  # a robot that does not come: the wait ends after max_wait_s
        waited += 1
    assert waited * 0.1 == pytest.approx(cfg.max_wait_s, abs=0.11)
    with pytest.raises(ConfigError):
        PersonConfig(escort_gap=1.0, escort_resume=1.5)


def test_steering_skips_a_waypoint_under_the_robot():
    """A path's waypoint within 5 cm of the robot gives no heading; steering for it the robot spun on the spot
    (the oracle follower fell seconds behind). It is skipped even where the next one is out of line of sight."""
    from agents.scripted import next_waypoint

    class Blind:
        def line_of_sight(self, a, b):
            return False

    path = np.array([[0.0, 0.0], [1.0, 0.02], [1.0, 1.0], [2.0, 1.0]])
    assert next_waypoint(Blind(), path, 1, np.array([1.0, 0.0])) == 2
    assert next_waypoint(Blind(), path, 1, np.array([0.9, 0.0])) == 1  # 10 cm: kept (it has a heading)
    assert next_waypoint(Blind(), path, 3, np.array([2.0, 1.0])) == 3  # the last one stays


def test_person_speech_alternates_talk_and_silence():
    from sonicverse_core.world.person import PersonConfig, speech_track

    cfg = PersonConfig(talk_s=(2.0, 3.0), silence_s=(2.5, 4.0))
    x, spans = speech_track(40.0, 16000, np.random.default_rng(0), cfg, "en-us")
    assert x.dtype == np.float32 and np.all(np.isfinite(x)) and np.abs(x).max() <= cfg.speech_peak + 1e-6
    assert spans[0][0] == 0.0  # it starts by talking
    gaps = [b[0] - a[1] for a, b in zip(spans, spans[1:])]
    long_gaps = [g for g in gaps if g > 1.0]
    assert long_gaps and all(2.5 - 1e-6 <= g <= 4.0 + 0.6 + 1e-6 for g in long_gaps)  # silences of 2.5-4 s
    for a, b in spans:  # each utterance is where the track has sound, and between them it is quiet
        assert np.abs(x[int(a * 16000):int(b * 16000)]).max() > 0.1
    quiet = np.ones(len(x), bool)
    for a, b in spans:
        quiet[int(a * 16000):int(b * 16000) + 1] = False
    assert np.abs(x[quiet]).max() == 0.0


def test_the_robot_collides_with_the_person_and_may_move_away():
    w = _world()
    x, y = w.grid.sample(np.random.default_rng(5), 1)[0]
    w.place_robot(x, y, 0.0)
    w.bodies["person"] = (np.array([x + 0.6, y]), 0.22)  # 0.6 m ahead
    for _ in range(20):
        w.drive([1.0, 1.0], 0.1)
    gap = math.hypot(w.pose[0] - (x + 0.6), w.pose[1] - y)
    assert w.bumped and gap >= 0.22 + w.robot.radius - 1e-9
    w.bodies["person"] = (np.array([w.pose[0] + 0.1, w.pose[1]]), 0.22)  # the person stepped onto the robot
    before = w.pose[0]
    w.drive([-1.0, -1.0], 0.1)  # backing away is allowed
    assert w.pose[0] < before - 0.02


def test_the_robots_camera_sees_the_person():
    env = T.make_env("SpeakerFollowing", scenes=HOME, sensors=("depth", "rgb"))
    env.reset(seed=2)
    w, p = env.home.world, env.task.person
    w.bodies = {}
    # put the person 1.5 m in front of the robot's camera (wherever the robot stands, facing the person)
    d = p.pos - w.pose[:2]
    yaw = math.degrees(math.atan2(d[1], d[0]))
    w.pose = np.array([*w.pose[:2], yaw])
    env.move_actor("person", p.pose)
    img = env._camera().render(*w.camera)
    centre = img["depth"][env.cfg.height // 2 - 20, env.cfg.width // 2]  # above the horizon: the torso
    dist = float(np.hypot(*d))
    assert abs(centre - (dist - 0.8 * p.cfg.radius)) < 0.15
    away = np.eye(4)
    away[:3, 3] = (100.0, 100.0, 100.0)
    env.move_actor("person", away)
    far = env._camera().render(*w.camera)["depth"][env.cfg.height // 2 - 20, env.cfg.width // 2]
    assert far == 0 or far > centre + 0.3  # without the person the ray goes on to the wall
    env.close()


# --- speaker following ------------------------------------------------------------------------------------------
def _episode(agent, seed, **kw):
    from agents import make_agent

    env = T.make_env("SpeakerFollowing", scenes=HOME, **kw)
    obs, info = env.reset(seed=seed)
    ag = make_agent(agent, np.random.default_rng(seed), "SpeakerFollowing")
    ag.reset(env, obs, info)
    done = False
    while not done:
        obs, r, term, trunc, info = env.step(ag.act(obs, info))
        done = term or trunc
    env.close()
    return info["metrics"], env


def test_speaker_following_oracle_keeps_close_and_catches():
    m, env = _episode("oracle", 0)
    assert m["catch_success"] == 1.0 and m["person_finished"] == 1.0
    assert m["time_in_band"] >= 0.8 and m["lost_s"] == 0.0
    d = np.array(env.task.distances)
    walking = np.array(env.task.walking)
    assert walking[0] and not walking[-1]  # the person stopped before the end
    assert m["time_in_band"] == pytest.approx(np.mean((d[walking] >= 1.0) & (d[walking] <= 2.5)))
    assert m["mean_distance_m"] == pytest.approx(d.mean())
    assert d[-1] <= 1.0  # caught: within 1 m and stopped


def test_speaker_following_scripted_follows_by_ear_and_eye_on_the_map():
    """The map follower keeps the walking person in the band and catches them; without its camera (audio and
    odometry only) it does worse on the same episode: what it sees is part of how it follows."""
    m, env = _episode("scripted", 2)
    assert m["catch_success"] == 1.0 and m["time_in_band"] >= 0.6 and m["collisions"] <= 20
    blind, _ = _episode("scripted", 2, sensors=("audio", "pose"))
    assert blind["time_in_band"] < m["time_in_band"] - 0.2


def test_speaker_following_episode_definition():
    from sonicverse_core.tasks.following import FollowEpisode

    env = T.make_env("SpeakerFollowing", scenes=HOME, sensors=("pose",))
    for seed in range(4):
        env.reset(seed=seed)
        ep, w, p = env.episode, env.home.world, env.task.person
        assert 1.2 - 0.05 <= env.task.dist <= 2.2 + 0.05  # starts close, behind the person
        assert 6.0 <= p.length <= 25.0 + 1.0 and len(ep.route) >= 3
        rooms = [next((r.name for r in w.scene.rooms if r.contains(np.array([q]))[0]), None) for q in ep.route]
        assert all(a != b for a, b in zip(rooms, rooms[1:]))  # each place in another room
        assert FollowEpisode.from_json(ep.to_json()) == ep
    env.reset(seed=99, options={"episode": ep.to_json()})  # an episode replayed from its JSON
    assert env.episode == ep and np.allclose(env.task.person.route, ep.route)
    # the catch rule: next to the stopped person, standing still -> success, +10
    env.reset(seed=0)
    p, w = env.task.person, env.home.world
    while not p.finished:
        p.advance(0.5)
    w.bodies = {}
    for q in w.grid.sample(np.random.default_rng(0), 400):
        if 0.5 < np.hypot(*(q - p.pos)) < 0.8 and w.grid.line_of_sight(q, p.pos):
            w.place_robot(q[0], q[1], 0.0)
            break
    for k in range(9):  # standing still for a second (10 steps): not yet "stopped" before that
        obs, r, term, trunc, info = env.step(np.zeros(2, np.float32))
        assert not term, k
    obs, r, term, trunc, info = env.step(np.zeros(2, np.float32))
    assert term and info["is_success"] and r > 9.0
    assert info["metrics"]["catch_success"] == 1.0


def test_random_follower_loses_the_person():
    m, _ = _episode("random", 1)
    assert m["catch_success"] == 0.0


# --- orientation training ---------------------------------------------------------------------------------------
def test_simulated_participant_matches_its_analytic_errors():
    """10 degrees of noise: mean |error| after resolving reversals = 10 sqrt(2/pi) = 7.98; reversals at 10%."""
    from sonicverse_core.tasks.orientation import OrientationTraining, SimulatedListener

    ot = OrientationTraining(trials=1000, staircase="none", render=False)
    rows = ot.run(SimulatedListener(noise_deg=10.0, front_back=0.1), np.random.default_rng(0))
    s = ot.summary(rows)
    assert abs(s["azimuth_error_deg"]["mean"] - 10 * math.sqrt(2 / math.pi)) <= 1.5
    assert abs(s["front_back_confusion_rate"]["mean"] - 0.1) <= 0.03
    assert s["trials"] == 1000
    # a participant who learns gets better
    ot2 = OrientationTraining(trials=400, staircase="none", render=False)
    rows2 = ot2.run(SimulatedListener(noise_deg=10.0, front_back=0.2, learning_rate=0.01), np.random.default_rng(1))
    e = np.array([r["azimuth_error_deg"] for r in rows2])
    assert e[-100:].mean() < 0.6 * e[:100].mean()


def test_staircase_follows_levitt():
    from sonicverse_core.tasks.orientation import Staircase

    s = Staircase(1.0, 0.5, 0.01, 2.0, harder_is_lower=True, down=2)
    assert s.update(True) == 1.0 and s.update(True) == 0.5  # two right: harder
    assert s.update(False) == 1.0  # one wrong: easier (a reversal)
    s.update(True), s.update(True)  # harder again (a reversal)
    assert s.reversals == [0.5, 1.0] and s.threshold == pytest.approx(math.sqrt(0.5))
    # on a simulated observer the 1-up-2-down track converges where p(correct) = 0.707
    rng = np.random.default_rng(0)
    s = Staircase(1.0, 0.8, 0.001, 10.0, harder_is_lower=True, down=2)
    p_correct = lambda x: 1 / (1 + (0.2 / x) ** 3)  # noqa: E731 - a psychometric function
    for _ in range(3000):
        s.update(rng.random() < p_correct(s.level))
    levels = np.array(s.history[500:])
    assert abs(np.mean([p_correct(x) for x in levels]) - 0.707) < 0.05


def test_orientation_stimuli_are_rendered_on_the_right_side():
    """The rendered stimulus's interaural delay (direct sound) has the target's side and Woodworth's size."""
    from sonicverse_core.tasks.orientation import OrientationTraining, _itd_us

    ot = OrientationTraining(trials=1)
    for sound in ("straight_chair/0", "toilet/0"):
        for az in (60.0, -60.0, 120.0, -120.0):
            audio = ot.render({"sound": sound, "azimuth": az, "elevation": 0.0, "distance": 2.0}, 0.5)
            assert np.all(np.isfinite(audio)) and np.abs(audio).max() <= 1.0
            lat = math.radians(90 - abs(abs(az) - 90))  # lateral angle
            woodworth = 0.0875 / 343.0 * (lat + math.sin(lat)) * 1e6
            itd = _itd_us(audio, 16000)
            assert np.sign(itd) == np.sign(az) and abs(abs(itd) - woodworth) < 130, (sound, az, itd)


def test_walk_trials_and_scoring():
    from sonicverse_core.tasks.orientation import OrientationTraining, SimulatedListener, score_turn

    assert score_turn(30.0, 150.0) == (0.0, True)  # a pure front-back confusion
    assert score_turn(90.0, 100.0) == (10.0, False)  # on the axis: never a reversal
    assert score_turn(10.0, -5.0) == (15.0, False)
    ot = OrientationTraining(trials=30, mode="walk", render=False, staircase="none")
    rows = ot.run(SimulatedListener(noise_deg=5.0, front_back=0.0), np.random.default_rng(0))
    s = ot.summary(rows)
    assert s["walk_success"]["mean"] >= 0.9 and 0.7 <= s["path_efficiency"]["mean"] <= 1.0


def test_a_vr_session_never_replaces_an_earlier_persons_csv(tmp_path):
    """A person's VR sessions cannot be played again: `task run --backend desktop|openvr --out DIR` over a CSV an
    earlier session left is refused before any window, audio or scene opens, the file untouched."""
    from app.tasks.run import run_in_vr

    for task, name in (("speaker-following", "speaker-following_scripted_desktop_s0.csv"),
                       ("orientation-training", "orientation-training_simulated_openvr_s3.csv")):
        old = tmp_path / name
        old.write_text("episode,time_in_band\n0,0.91\n")
        seed = 3 if "openvr" in name else 0
        with pytest.raises(ConfigError, match="earlier session's rows.*--overwrite"):
            run_in_vr(task, None, 1, seed=seed, backend=name.split("_")[-2], out=tmp_path)
        assert old.read_text() == "episode,time_in_band\n0,0.91\n"


def test_a_simulated_training_run_never_replaces_one_with_other_settings(tmp_path, capsys):
    """`task run orientation-training --out DIR`: the same settings again replace the CSV (the run is
    deterministic); other settings, or a CSV without its settings file, are refused in one line with the file
    untouched, unless --overwrite."""
    from app.cli import main

    base = ["task", "run", "orientation-training", "--trials", "6", "--mode", "turn", "--out", str(tmp_path)]
    csv_path = tmp_path / "orientation-training_simulated_s0.csv"
    assert main(base) == 0
    first = csv_path.read_text()
    assert len(first.splitlines()) == 7 and json.loads((tmp_path / (csv_path.name + ".json")).read_text())["seed"] == 0
    assert main(base) == 0 and csv_path.read_text() == first  # the same run again: the same rows
    capsys.readouterr()
    assert main(base[:4] + ["8"] + base[5:]) == 2  # 8 trials where 6 were run
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "other settings: trials 6 (now 8)" in err and "--overwrite" in err
    assert main(base + ["--noise", "30"]) == 2 and "noise_deg 10.0 (now 30.0)" in capsys.readouterr().err
    assert csv_path.read_text() == first
    (tmp_path / (csv_path.name + ".json")).write_text("[1]\n")  # JSON, but not a run's settings
    assert main(base) == 2 and "unreadable" in capsys.readouterr().err and csv_path.read_text() == first
    (tmp_path / (csv_path.name + ".json")).unlink()
    assert main(base) == 2 and "missing" in capsys.readouterr().err and csv_path.read_text() == first
    assert main(base[:4] + ["8"] + base[5:] + ["--overwrite"]) == 0
    assert len(csv_path.read_text().splitlines()) == 9


def test_task_run_command(tmp_path, capsys):
    from app.cli import main

    assert main(["task", "run", "orientation-training", "--trials", "12", "--mode", "mixed", "--blocks", "2",
                 "--out", str(tmp_path), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    for k in TASKS["OrientationTraining"].metrics + ("trials",):
        assert k in res
    assert res["trials"] == 24 and (tmp_path / "orientation-training_simulated_s0_learning_curve.png").stat().st_size
    assert set(res["staircase"]) == {"turn", "walk"}  # one track per trial kind
    assert len((tmp_path / "orientation-training_simulated_s0.csv").read_text().splitlines()) == 25
    assert main(["task", "run", "speaker-following", "--agent", "oracle", "--episodes", "1", "--max-steps", "60",
                 "--homes", "1", "--out", str(tmp_path), "--maps", str(tmp_path / "maps"), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert set(TASKS["SpeakerFollowing"].metrics) <= set(res) and res["episodes"] == 1
    assert (tmp_path / "maps" / "episode_0000.png").stat().st_size > 0
    assert main(["task", "run", "speaker-following", "--agent", "gan"]) == 2
    assert "unknown agent" in capsys.readouterr().err
    assert main(["task", "list", "--json"]) == 0
    assert {r["task"] for r in json.loads(capsys.readouterr().out)} == {s.cli for s in TASKS.values()}


def test_scripted_followers_senses():
    """The two senses the scripted agents rely on: onset-weighted GCC-PHAT finds the leading ear in a
    reverberant-like signal, and the map-based detector finds the person standing in front of the camera (what
    stands at chest height on open floor of the map) and clears the floor it sees empty."""
    from agents.retrieval import SpeakerBelief
    from agents.scripted import onset_gcc_phat

    sr, rng = 16000, np.random.default_rng(0)
    burst = np.zeros(1600)
    burst[800:1200] = rng.standard_normal(400)  # an onset in the middle of the block
    tail = 0.3 * rng.standard_normal((2, 1600))  # steady diffuse noise before it: no onset there
    for lag in (5, -5):  # the right ear hears the burst 5 samples late: the left leads
        block = np.stack([burst, np.roll(burst, lag)]) + 0.02 * rng.standard_normal((2, 1600))
        cc, w = onset_gcc_phat(block, tail[:, -480:], sr, 0.00066)
        assert w > 0 and int(np.argmax(cc)) - (len(cc) - 1) // 2 == lag
    env = T.make_env("SpeakerFollowing", scenes=HOME, sensors=("depth",))
    env.reset(seed=2)
    w, p = env.home.world, env.task.person
    d = p.pos - w.pose[:2]
    w.pose = np.array([*w.pose[:2], math.degrees(math.atan2(d[1], d[0])) + 10.0])  # the person 10 deg to the right
    depth = env._camera().render(*w.camera)["depth"]
    fx = (env.cfg.width / 2) / math.tan(math.radians(env.cfg.hfov) / 2)
    from sonicverse_core.world.person import person_mesh

    assert env._actors["person"][0] is person_mesh(p.cfg.height, p.cfg.radius)  # the body of parts, not a cylinder
    env.close()
    b = SpeakerBelief(env.task.map.grid, 16000)
    behind = b.xy[int(np.argmax(np.hypot(*(b.xy - p.pos).T)))]  # the farthest place: out of view
    before = b.mass(0, p.pos, 0.25), b.mass(0, behind, 0.25)
    seen = b.see(depth, w.pose[:2], w.pose[2], fx, w.robot.camera_height)
    assert seen is not None and np.hypot(*(seen - p.pos)) < 0.3, (seen, p.pos)
    # one look moves belief towards where the camera saw the person (repeated looks compound it)
    assert b.mass(0, p.pos, 0.25) / before[0] > 1.4 * b.mass(0, behind, 0.25) / before[1]
    ahead = w.pose[:2] + 0.5 * (p.pos - w.pose[:2])  # halfway to them, in view and empty
    assert b.mass(0, ahead, 0.2) < 0.5 * b.mass(1, ahead, 0.2)  # seen empty (the audio-only belief is not)


def test_hrtf_decoding_filters_are_fitted_once_per_set():
    """Envs build a renderer per episode: the least-squares ambisonic decoder is cached on the shared HRTF set."""
    from sonicverse_core.acoustics.renderer import _hrtf

    h = _hrtf("kemar", 16000, 256)
    a, bulk = h.ambisonic_filters(2, 512)
    b, bulk2 = h.ambisonic_filters(2, 512)
    assert a is b and bulk == bulk2 and not a.flags.writeable
    c, _ = h.ambisonic_filters(1, 512)
    assert c.shape[0] == 4 and a.shape[0] == 9


# --- voice retrieval --------------------------------------------------------------------------------------------
def _retrieval(agent, seed, **kw):
    from agents import make_agent

    env = T.make_env("VoiceRetrieval", scenes=HOME, sensors=("audio", "pose"), **kw)
    obs, info = env.reset(seed=seed)
    ag = make_agent(agent, np.random.default_rng(seed), "VoiceRetrieval")
    ag.reset(env, obs, info)
    done, heard = False, []
    while not done:
        obs, r, term, trunc, info = env.step(ag.act(obs, info))
        heard.append(float(np.sqrt(np.mean(obs["audio"] ** 2))))
        done = term or trunc
    env.close()
    return info["metrics"], env, np.array(heard), term


def test_voice_retrieval_oracle_fetches_and_the_scores_follow_their_definitions():
    m, env, heard, term = _retrieval("oracle", 3)
    t, w = env.task, env.home.world
    assert term and m["sr"] == 1.0 and m["command_accuracy"] == 1.0
    assert t.placed in t.targets and np.hypot(*(w.scene.object(t.placed).position[:2] - t.person_xy)) <= 1.0
    assert env.episode.category in t.placed and env.episode.text.endswith(
        {"straight_chair": "chair"}.get(env.episode.category, env.episode.category))
    assert 0 < m["spl"] <= 1.0 and m["spl"] == pytest.approx(t.shortest / max(t.shortest, env.path_length))
    assert heard[:20].max() > 0  # the command reaches the robot's ears at the start


def test_voice_retrieval_interactions():
    env = T.make_env("VoiceRetrieval", scenes=HOME, sensors=("pose",))
    env.reset(seed=1)
    w, t = env.home.world, env.task
    _, r, term, _, _ = env.step([0.0, 0.0, 1.0])  # nothing in reach: nothing happens
    assert w.carried is None and not term
    from sonicverse_core.tasks.retrieval import approach_points

    name = next(n for n in t.targets if len(approach_points(w, n)))
    spot = approach_points(w, name)[0]
    v = w.scene.object(name).position[:2] - spot
    w.place_robot(spot[0], spot[1], math.degrees(math.atan2(v[1], v[0])))
    _, r, term, _, info = env.step([0.0, 0.0, 1.0])
    assert info["carrying"] is not None and not term and r > 0.5 and t.understood == (info["carrying"] in t.targets)
    assert env.source.gain == 0.0 and t.calls.gain == 1.0  # the person stops asking and calls
    _, r, term, _, info = env.step([0.0, 0.0, 1.0])  # put down far from the person: the episode ends, failed
    if term:
        assert not info["success"] and info["metrics"]["sr"] == 0.0
    env.close()


def test_voice_retrieval_random_never_succeeds():
    m, env, _, _ = _retrieval("random", 2, max_steps=60)
    assert m["sr"] == 0.0 and m["command_accuracy"] == 0.0


def test_voice_retrieval_semantic_map_and_the_speaker_estimate_it_scores():
    env = T.make_env("VoiceRetrieval", scenes=HOME, sensors=("pose",))
    with pytest.raises(ConfigError, match="reset"):
        env.semantic_map()
    obs, _ = env.reset(seed=4)
    m, t, w = env.semantic_map(), env.task, env.home.world
    names = {o.name for o in m.objects}
    assert names == {o.name for o in w.scene.objects} and "person" not in names  # people are not on the map
    assert {o.category for o in m.objects if o.movable} >= {env.episode.category}
    xy, yaw = m.to_map(obs["pose"])
    assert np.allclose(xy, w.pose[:2], atol=1e-4) and abs((yaw - w.pose[2] + 180) % 360 - 180) < 1e-3
    for _ in range(5):  # odometry stays on the map as the robot turns and drives
        obs, *_ = env.step([0.3, 0.8, -1.0])
    xy, yaw = m.to_map(obs["pose"])
    assert np.allclose(xy, w.pose[:2], atol=1e-3) and abs((yaw - w.pose[2] + 180) % 360 - 180) < 1e-2
    for bad in ({"speaker": (np.nan, 1.0)}, {"speaker": (1.0,)}, {"target": (1.0, 2.0)}):
        with pytest.raises(ConfigError):
            env.report(**bad)
    # an estimate 90 degrees off at the same range, as the robot sees it: 90 degrees, 0 m
    p, r = t.person_xy, w.pose[:2]
    v = p - r
    env.report(speaker=tuple(r + np.array([-v[1], v[0]])))
    env.report(speaker=tuple(p))  # only the first report counts
    m2 = env.metrics(False)
    assert m2["speaker_azimuth_error_deg"] == pytest.approx(90.0) and m2["speaker_distance_error_m"] < 1e-9
    env.close()
    other = T.make_env("AudioGoal", scenes=HOME, sensors=("pose",))
    other.reset(seed=0)
    with pytest.raises(ConfigError, match="no semantic map"):
        other.semantic_map()
    with pytest.raises(ConfigError, match="scores no estimates"):
        other.report(speaker=(0.0, 0.0))
    other.close()


def test_mean_ci95_leaves_out_episodes_without_the_measure():
    from sonicverse_core.tasks.metrics import mean_ci95

    ci = mean_ci95([1.0, float("nan"), 2.0, 3.0, 4.0])
    assert ci["n"] == 4 and ci["mean"] == 2.5 and ci["median"] == 2.5
    assert mean_ci95([float("nan")])["mean"] is None


def test_speaker_belief_hears_other_rooms_through_the_doorway_and_places_a_talker():
    """The belief's model of where sound comes from (a cell out of sight is heard from the last place on its way
    that the robot sees) and its estimate of a talker in the robot's room, from the full renderer (reverb on)."""
    from scipy.signal import resample_poly

    from agents.retrieval import SpeakerBelief
    from app.bench.recogniser import _localise, _scene_setup
    from sonicverse_core.world.person import utterance

    scene, world, probes = _scene_setup(HOME[0])
    b = SpeakerBelief(world.grid, 16000)
    p = b.xy[len(b.xy) // 2]
    via, length = b.arrivals(p)
    vis = b.visible(p)
    hidden = np.flatnonzero(~vis)
    assert len(hidden) > 100 and np.all(vis)  == False  # noqa: E712  (other rooms are out of sight)
    assert np.allclose(via[vis], b.xy[vis])  # in sight: heard from where it is
    nearest = [int(np.argmin(np.hypot(*(b.xy - v).T))) for v in via[hidden]]
    assert np.all(vis[nearest])  # out of sight: heard from a place the robot sees
    straight = np.hypot(*(b.xy - p).T)
    assert np.all(length >= straight - 1e-6) and np.all(length[hidden] > straight[hidden])
    speech = np.array(utterance("please bring me the cushion", "en-us", 160, 48000, 0.5))
    s16 = resample_poly(speech, 1, 3).astype(np.float32)
    x16 = np.r_[np.zeros(8000, np.float32), s16, np.zeros(16000, np.float32), s16]  # said twice, as in the bench
    rng = np.random.default_rng(0)
    errs = []
    room = max(scene.rooms, key=lambda r: np.ptp(r.footprint[:, 0]) * np.ptp(r.footprint[:, 1])).name
    while len(errs) < 6:
        pp, lp = world.base.sample(rng, 2, room=room)
        if not 1.5 <= np.hypot(*(pp - lp)) <= 4.0:
            continue
        z0 = scene.floor_z
        az, _ = _localise(scene, probes, b, x16, (pp[0], pp[1], z0 + 1.58), (lp[0], lp[1], z0 + 0.4),
                          float(rng.uniform(0, 360)))
        errs.append(az)
    assert np.median(errs) < 30.0, errs  # chance is 90


def test_voice_retrieval_scripted_agent_hears_fetches_and_delivers():
    """The scripted agent from its own sensors and the semantic map: it understands the command, reports where the
    voice came from, fetches an object of the category and puts it down by the person."""
    from agents import make_agent

    env = T.make_env("VoiceRetrieval", scenes=HOME)
    obs, info = env.reset(seed=1)
    ag = make_agent("scripted", np.random.default_rng(1), "VoiceRetrieval")
    ag.reset(env, obs, info)
    done = False
    while not done:
        obs, r, term, trunc, info = env.step(ag.act(obs, info))
        done = term or trunc
    m = info["metrics"]
    assert ag.category == env.episode.category and m["command_accuracy"] == 1.0
    assert term and m["sr"] == 1.0 and 0 < m["spl"] <= 1.0
    assert m["same_room"] == 1.0 and m["speaker_azimuth_error_deg"] < 45.0  # chance: 90
    env.close()


def test_task_run_plays_in_jobs_and_resumes_as_eval_does(tmp_path, cli):
    """`task run --jobs 2` gives the rows and metrics of one process; `--resume` plays only the episodes its CSV
    lacks (a row kept from before stays as it is) and refuses the CSV of another run."""
    import csv

    from app.tasks.run import run_task
    from sonicverse_core.errors import ConfigError

    kw = {"max_steps": 30}
    two = run_task("speaker-following", "scripted", 3, seed=2, out=tmp_path, env_kwargs=kw, jobs=2)
    path = Path(two["csv"])
    whole = list(csv.DictReader(open(path, newline="")))
    assert [int(r["episode"]) for r in whole] == [0, 1, 2] and two["episodes"] == 3
    rows = whole[:2]  # as if stopped after two episodes, the first edited: the resumed run keeps it as it is
    rows[0] = {**rows[0], "reward": "12345"}
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    res = run_task("speaker-following", "scripted", 3, seed=2, out=tmp_path, env_kwargs=kw, resume=True)
    got = list(csv.DictReader(open(path, newline="")))  # episode 2 played again in one process: the jobs' row
    assert res["episodes"] == 3 and got[0]["reward"] == "12345" and got[1:] == whole[1:]
    with pytest.raises(ConfigError, match="its env differs"):
        run_task("speaker-following", "scripted", 3, seed=2, out=tmp_path, env_kwargs={"max_steps": 31},
                 resume=True)
    from app.tasks.evaluate import csv_name

    assert Path(two["csv"]).name == csv_name("speaker-following", "scripted", "test", 2) == \
        "speaker-following_scripted_test_s2.csv"
    assert csv_name("AudioGoal", "m:f", "test", 0, 100, "heard") == "AudioGoal_m.f_test_heard_s0_from100.csv"
    with pytest.raises(ConfigError, match="--resume is for robot tasks"):
        run_task("orientation-training", resume=True)
    r = cli("task", "run", "orientation-training", "--jobs", "2")
    assert r.returncode == 2 and "--jobs is for robot tasks" in r.stderr and len(r.stderr.strip().splitlines()) == 1
