import numpy as np
import pytest

from assets_manifest import entry, manifest
from assets_manifest import soundbank as sb
from sonicverse_core.errors import AssetError


def test_manifest_lists_every_sound_with_golden_hashes():
    m = manifest()
    for cat in sb.CATEGORIES:
        for v in range(sb.VARIANTS):
            e = m[f"sound/{cat}/{v}"]
            assert {"name", "kind", "licence", "origin", "sha256", "size"} <= set(e)
            assert sb.pcm_sha256(sb.sound(cat, v)) == e["sha256"], f"{cat}/{v} changed: regenerate the manifest"
    assert entry("hrtf/mit_kemar_normal_pinna")["kind"] == "hrtf"


def test_sounds_are_distinct_bounded_and_discontinuous():
    cents = []
    for cat in sb.CATEGORIES:
        x = sb.sound(cat, 0).astype(np.float64)
        assert 2.0 <= len(x) / sb.SAMPLE_RATE <= 5.0
        assert np.max(np.abs(x)) == pytest.approx(0.5, abs=1e-3)
        frames = x[: len(x) // 480 * 480].reshape(-1, 480)
        rms = np.sqrt(np.mean(frames ** 2, axis=1))
        assert np.mean(rms < 1e-3) > 0.02 or cat in ("shower", "toilet"), cat  # gaps of silence
        spec = np.abs(np.fft.rfft(x))
        f = np.fft.rfftfreq(len(x), 1 / sb.SAMPLE_RATE)
        cents.append(np.sum(f * spec) / np.sum(spec))
    # categories differ: spectral centroids spread over more than two octaves
    assert max(cents) / min(cents) > 4
    a, b = sb.sound("sofa", 0), sb.sound("sofa", 3)
    assert len(a) != len(b) or not np.allclose(a, b)
    assert set(sb.sound_names("heard")).isdisjoint(sb.sound_names("unheard"))


def test_bad_sound_names():
    with pytest.raises(AssetError):
        sb.sound("piano")
    with pytest.raises(AssetError):
        sb.sound("sofa", 9)
    with pytest.raises(AssetError):
        sb.by_name("sofa/x")


def test_speech_from_espeak():
    from assets_manifest.speech import speak

    x, sr = speak("bring me the cushion", sample_rate=16000)
    assert sr == 16000 and 1.0 < len(x) / sr < 4.0
    assert np.max(np.abs(x)) > 0.05
    assert np.all(np.abs(x[: int(0.3 * sr)]) == 0)  # padded with silence


def test_kemar_hrtf():
    from assets_manifest.hrtf import kemar

    h = kemar()
    assert h.hrirs.shape == (710, 2, 512) and h.sample_rate == 44100
    np.testing.assert_allclose(np.linalg.norm(h.directions, axis=1), 1.0, atol=1e-9)
    left = np.argmax(h.directions @ np.array([0, 1.0, 0]))  # the direction nearest +y (left)
    e = np.sum(h.hrirs[left].astype(np.float64) ** 2, axis=1)
    assert e[0] > 4 * e[1]  # a source on the left is louder in the left ear


def test_missing_sofa_file(tmp_path):
    from assets_manifest.hrtf import load_sofa

    with pytest.raises(AssetError, match="not found"):
        load_sofa(tmp_path / "none.sofa")


def test_the_shipped_recogniser_weights_match_the_manifest():
    from agents.voice import WEIGHTS
    from assets_manifest import sha256_file

    e = entry("asr/voice-commands")
    assert WEIGHTS.is_file() and sha256_file(WEIGHTS) == e["sha256"], "retrained? regenerate the manifest"
