"""The learned sound localiser (agents/localizer.py) and the agent built on it (agents/scripted.GanLocalizerAgent, the
gan baseline until session 51; agents/gan.py is now):
training end to end on a few frames, the shipped model's accuracy on test homes against chance, clear errors for bad
checkpoints, and the agent reaching sounds it never had privileged access to."""
import csv

import numpy as np
import pytest
import torch

from agents.localizer import LocalizerTrainConfig, SoundLocalizer, collect, errors, gcc_input, load, train


def test_gcc_input_peaks_at_the_interaural_delay():
    rng = np.random.default_rng(0)
    x = rng.normal(size=1600)
    k = 5  # the right ear hears it 5 samples later: the left leads
    audio = np.stack([x, np.concatenate([np.zeros(k), x[:-k]])])
    cc = gcc_input(audio, 16000)
    assert cc.shape == (27,) and int(np.argmax(cc)) - 13 == k
    assert not gcc_input(np.zeros((2, 1600)), 16000).any()


def test_training_writes_a_checkpoint_and_a_log(tmp_path):
    res = train(LocalizerTrainConfig(frames=120, val_frames=40, epochs=2, episode_steps=60, seed=2), tmp_path / "l")
    rows = list(csv.DictReader(open(tmp_path / "l" / "log.csv")))
    assert [int(r["epoch"]) for r in rows] == [0, 1] and float(rows[0]["bearing_median_deg"]) >= 0
    model, meta = load(res["checkpoint"])
    assert meta["train_frames"] == 120 and isinstance(model, SoundLocalizer)
    from sonicverse_core.errors import ConfigError

    with pytest.raises(ConfigError, match="exists"):
        train(LocalizerTrainConfig(frames=10), tmp_path / "l")
    bad = tmp_path / "bad.pt"
    torch.save({"arch": "av-nav"}, bad)
    with pytest.raises(ConfigError, match="not a Sonicverse sound-localiser"):
        load(bad)
    with pytest.raises(ConfigError, match="not found"):
        load(tmp_path / "none.pt")


@pytest.mark.slow  # 12 s: the model card's finding about the shipped file; `make test-slow` checks it
def test_the_shipped_localiser_is_at_chance_on_steady_sounds_in_reverberant_homes():
    """The model card's finding, on test homes (never trained on), headings uncorrelated with the sound: one step of
    a steady sound gives a median bearing error near chance (90 degrees). If this fails because the error fell, the
    localiser (or the homes' acoustics) improved: update agents/checkpoints/sound-localizer.md and the README."""
    from agents.learned import CHECKPOINTS

    model, meta = load(CHECKPOINTS / "sound-localizer.pt")
    assert 20_000 <= meta["train_frames"] < 20_010 and meta["config"]["task"] == "SemanticAudioNav"
    data = collect("SemanticAudioNav", "test", 300, np.random.default_rng(11))
    e = errors(model, data)
    assert e["frames"] == 300 and np.all(np.isfinite(data["y"]))
    assert 70 < e["bearing_median_deg"] < 110
    # the labels' bearings cover the circle (the collection turns the robot at random)
    b = np.degrees(np.arctan2(data["y"][:, 1], data["y"][:, 0]))
    assert np.histogram(b, bins=4, range=(-180, 180))[0].min() > 300 / 4 * 0.5


def test_the_localiser_agent_turns_once_then_drives_to_its_estimate():
    import math

    from agents.scripted import GanLocalizerAgent as GanAgent
    from sonicverse_core.tasks import make_env

    env = make_env("AudioGoal", split="test", homes=2, sensors=("depth", "audio", "spectrogram", "pose", "bump"))
    try:
        obs, info = env.reset(seed=3)
        ag = GanAgent(np.random.default_rng(0))
        ag.reset(env, obs, info)
        spin, turned = ag.spin_left, 0.0
        for _ in range(spin):
            a = ag.act(obs, info)
            assert a[0] == -a[1] and a[1] > 0  # on the spot, to the left
            obs, _, term, trunc, info = env.step(a)
        x, y, s_, c = obs["pose"]
        assert math.hypot(x, y) < 0.05 and ag._estimate() is not None and ag.heard > 0
        start = obs["pose"][:2].copy()
        for _ in range(30):
            a = ag.act(obs, info)
            # after every step's votes its plan leads to its estimate (within the replanning's 0.4 m; the path's
            # last waypoint is the goal's map cell), or it circles an estimate it has reached. Where the estimate
            # lies is the localiser's business (near chance, README): the test is that the agent goes there.
            if ag.circle == 0:
                assert np.linalg.norm(ag.goal - ag._estimate()) <= 0.4 + 1e-9
                assert np.linalg.norm(ag.path[-1] - ag.goal) <= ag.CELL
            obs, _, term, trunc, info = env.step(a)
            if term or trunc:
                break
        assert term or ag.circle > 0 or np.linalg.norm(obs["pose"][:2] - start) > 0.5  # it drove, it did not spin
        assert np.all(np.isfinite(ag.votes)) and ag.votes.max() > 0
    finally:
        env.close()
