"""The spoken-command recogniser (agents/voice.py): its features, its shipped weights on voices it was not trained
on (clean and heard across a room), and its errors."""
import numpy as np
import pytest

from agents.voice import CLASSES, SPOKEN, TRAIN_VARIANTS, CommandRecogniser, command_text, features
from sonicverse_core.errors import AssetError, ConfigError
from sonicverse_core.world.person import VOICES, utterance

CARRIED = ("cushion", "stool", "straight_chair", "picture")


@pytest.fixture(scope="module")
def rec():
    return CommandRecogniser()


def test_the_person_voices_are_held_out():
    variants = {v.split("+")[1] if "+" in v else "" for v in VOICES}
    assert not variants & set(TRAIN_VARIANTS) and "" not in TRAIN_VARIANTS


def test_features_remove_gain_and_a_fixed_colouring():
    """Log-mel minus each band's utterance mean: a gain, or any filter flat within a band, changes nothing."""
    from scipy.signal import lfilter

    x = np.array(utterance(command_text("cushion"), "en-us", 150, 16000, 0.5))
    f = features(x)
    assert f.shape[1] == 40 and abs(len(f) - (len(x) - 400) // 160 - 1) <= 1
    np.testing.assert_allclose(features(0.05 * x), f, atol=1e-3)
    dull = lfilter([0.5], [1, -0.5], x)  # a one-pole low-pass: a smooth tilt, nearly constant within each band
    assert np.abs(features(dull) - f)[:, 5:35].mean() < 0.6 * np.abs(f)[:, 5:35].mean()
    with pytest.raises(ConfigError):
        features(np.array([0.0, np.nan]))


def test_clean_commands_in_unseen_voices(rec):
    right = 0
    for voice in VOICES:
        for k, cat in enumerate(CARRIED):
            x = np.array(utterance(command_text(cat, k + 1), voice, 150, 48000, 0.5))
            right += rec.recognise(x, 48000, allowed=CARRIED).category == cat
    assert right >= 0.9 * len(VOICES) * len(CARRIED), right
    for phrase in ("follow me please", "stay close to me"):
        x = np.array(utterance(phrase, "en-us+f2", 150, 48000, 0.5))
        assert rec.recognise(x, 48000).category == "other"


def test_commands_heard_across_a_room(rec):
    """Rendered binaurally (HRTF, early reflections, late reverb) 3.5 m away in a 6 x 5 x 3 m room."""
    from sonicverse_core.acoustics.probes import scene_probes
    from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene("shoebox:6x5x3")
    probes = scene_probes(scene)
    right = 0
    for i, cat in enumerate(CARRIED * 2):
        x = np.array(utterance(command_text(cat, i), VOICES[i % len(VOICES)], 165, 48000, 0.5))
        r = AcousticRenderer(scene, RenderConfig(), probes)
        r.add_source(x, (4.5, 3.0, 1.58), loop=False, directivity=0.3, forward=(-1, -0.3, 0))
        r.add_listener((1.2, 1.8, 0.4), 30.0 * i)
        heard = r.render(len(x) / 48000 + 0.4)[0].mean(0)
        right += rec.recognise(heard, 48000, allowed=CARRIED).category == cat
    assert right >= 7, right


def test_allowed_restricts_the_answer(rec):
    x = np.array(utterance(command_text("stool"), "en-gb", 150, 48000, 0.5))
    p = rec.posteriors(x, 48000)
    assert p.shape == (len(CLASSES),) and abs(p.sum() - 1) < 1e-5
    got = rec.recognise(x, 48000, allowed=("bed", "sofa"))
    assert got.category in ("bed", "sofa", "other")
    with pytest.raises(ConfigError):
        rec.recognise(x, 48000, allowed=("spaceship",))
    with pytest.raises(ConfigError):
        command_text("spaceship")
    assert set(SPOKEN) < set(CLASSES)


def test_broken_weights_are_refused(tmp_path):
    with pytest.raises(AssetError, match="not found"):
        CommandRecogniser(tmp_path / "none.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(AssetError, match="cannot read"):
        CommandRecogniser(bad)
