"""The late tail (issue: sound between rooms, item 4): it starts after the direct sound and the mixing time, has no
discrete echoes at its onset, decays at the probe's RT60 in every band, carries the HRTF set's diffuse-field
interaural coherence and the same energy in both ears; a room whose surfaces absorb everything builds none."""
import numpy as np
import pytest
from scipy.signal import butter, sosfilt

from sonicverse_core.acoustics.probes import Probe
from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig
from sonicverse_core.scene.materials import BANDS

FS = 48000
SRC, LIS = np.array([1.0, 1.0, 1.5]), np.array([7.0, 5.0, 1.5])
RT = np.array([1.2, 1.1, 1.0, 0.9, 0.8, 0.75, 0.7, 0.6, 0.5])


def _probe():
    return Probe(np.array([4.0, 3.0, 1.5]), RT.copy(), RT.copy(), np.zeros(3), np.array([8.0, 6.0, 3.0]),
                 ("PlasterRough",) * 6, 1.0)


def _late(output="binaural", seconds=1.6):
    """(late part, direct part) of the impulse response from SRC to LIS: the full render minus the direct-only one."""
    outs = []
    for late in (True, False):
        r = AcousticRenderer(None, RenderConfig(output=output, occlusion=False, early_reflections=False,
                                                late_reverb=late), probes=[_probe()])
        x = np.zeros(FS * 2, np.float32)
        x[0] = 1.0
        r.add_source(x, SRC, loop=False)
        r.add_listener(LIS)
        outs.append(r.render(seconds)[0].astype(np.float64))
    return outs[0] - outs[1], outs[1]


@pytest.fixture(scope="module")
def binaural():
    return _late()


def test_the_tail_starts_after_the_direct_sound_and_the_mixing_time(binaural):
    late, direct = binaural
    arrival = int(np.argmax(np.abs(direct).max(0) > 1e-4 * np.abs(direct).max()))
    first = int(np.argmax(np.abs(late).max(0) > 1e-7))
    t_mix = np.sqrt(8 * 6 * 3) / 1000  # Polack: sqrt(V) ms
    assert first >= arrival + int(0.9 * t_mix * FS), (first, arrival)
    assert first <= arrival + int(1.5 * t_mix * FS) + 256  # and not much later


def test_no_discrete_echoes_at_the_onset(binaural):
    """No 5 ms window of the late part more than 6 dB above its smoothed decay (the FDN's first passes were
    sparse pulses up to 12 dB above the direct sound)."""
    late, _ = binaural
    e = (late ** 2).sum(0)
    first = int(np.argmax(e > 0))
    w = int(0.005 * FS)
    win = np.add.reduceat(e[first:first + 60 * w], np.arange(0, 60 * w, w))
    t = np.arange(len(win))
    fit = np.polyval(np.polyfit(t, 10 * np.log10(win + 1e-30), 1), t)  # the smoothed (exponential) decay
    assert np.max(10 * np.log10(win + 1e-30) - fit) < 6.0


def _t30(x):
    edc = np.cumsum((x ** 2)[::-1])[::-1]
    db = 10 * np.log10(edc / edc[0] + 1e-30)
    i5, i35 = np.argmax(db <= -5), np.argmax(db <= -35)
    slope = np.polyfit(np.arange(i5, i35) / FS, db[i5:i35], 1)[0]
    return -60 / slope


@pytest.mark.parametrize("band", range(len(BANDS)))
def test_per_band_decay_matches_the_probe(binaural, band):
    late, _ = binaural
    fc = BANDS[band]
    if fc * np.sqrt(2) >= FS / 2:
        pytest.fail("band above Nyquist")  # never at 48 kHz: every band is checked
    sos = butter(4, [fc / np.sqrt(2), min(fc * np.sqrt(2), 0.45 * FS)], "bandpass", fs=FS, output="sos")
    y = sosfilt(sos, late[0])
    start = int(np.argmax(np.abs(late[0]) > 0))
    if band <= 1:  # low bands: their 1.2 s decay needs the whole window
        assert _t30(y[start:]) == pytest.approx(RT[band], rel=0.2)
    else:
        assert _t30(y[start:]) == pytest.approx(RT[band], rel=0.12)


def test_interaural_coherence_and_colour_follow_the_hrtf(binaural):
    from sonicverse_core.acoustics.renderer import _hrtf

    late, _ = binaural
    _, rho = _hrtf("kemar", FS, int(round(0.004 * FS))).diffuse_field
    got = []
    for b, fc in enumerate(BANDS[2:8], start=2):
        sos = butter(4, [fc / np.sqrt(2), fc * np.sqrt(2)], "bandpass", fs=FS, output="sos")
        a, c = sosfilt(sos, late[0]), sosfilt(sos, late[1])
        got.append(abs(np.sum(a * c)) / np.sqrt(np.sum(a * a) * np.sum(c * c)))
        assert got[-1] == pytest.approx(rho[b], abs=0.15), (fc, got[-1], rho[b])
    assert got[0] > 0.4 and got[-1] < 0.15  # coherent at 250 Hz, incoherent at 4 kHz
    e = (late ** 2).sum(1)
    assert abs(10 * np.log10(e[0] / e[1])) < 0.5  # the same tail energy in both ears


def test_mono_output_has_the_same_tail_in_both_channels():
    late, _ = _late("mono", 0.6)
    assert np.abs(late).max() > 0 and np.allclose(late[0], late[1], atol=1e-7)


def test_a_room_that_absorbs_everything_builds_no_reverb():
    from sonicverse_core.acoustics.probes import reverb_free, scene_probes
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene("shoebox:6x5x3?material=Transparent")
    assert "absorbs everything" in reverb_free(scene)
    assert scene_probes(scene) is None
    r = AcousticRenderer(scene, RenderConfig(), probes=scene_probes(scene))
    assert "late_reverb" not in r.subsystems and "early_reflections" not in r.subsystems
    x = np.zeros(FS, np.float32)
    x[0] = 1.0
    r.add_source(x, (1.0, 1.0, 1.5), loop=False)
    r.add_listener((4.0, 3.0, 1.5))
    y = r.render(0.3)[0].astype(np.float64)
    arrival = int(np.linalg.norm([3.0, 2.0, 0.0]) / 343 * FS)
    assert np.sum(y[:, arrival + 600:] ** 2) < 1e-12 * np.sum(y ** 2)  # nothing after the direct sound
    assert reverb_free(load_scene("shoebox:6x5x3")) is None


def _edt(x):
    """Early decay time: the Schroeder curve's first 10 dB, extrapolated to 60."""
    edc = np.cumsum((x ** 2)[::-1])[::-1]
    db = 10 * np.log10(edc / edc[0] + 1e-30)
    i10 = int(np.argmax(db <= -10))
    return -60 / np.polyfit(np.arange(i10) / FS, db[:i10], 1)[0]


@pytest.mark.parametrize("factor", [0.7, 1.3])
def test_the_tail_falls_first_at_the_probes_early_decay_time(factor):
    """A probe whose bake says the first 10 dB fall faster (EDT 0.7 x RT60, as in a room with an absorbing ceiling)
    or slower (1.3 x) than the rest: the tail's Schroeder curve falls its first 10 dB at the bake's EDT and the
    rest at its RT60 (T30); ``tail_edt=False`` gives one slope (EDT = RT60)."""
    probe = _probe()
    probe.edt = RT * factor
    for on in (True, False):
        outs = []
        for late in (True, False):
            r = AcousticRenderer(None, RenderConfig(output="mono", occlusion=False, early_reflections=False,
                                                    late_reverb=late, tail_edt=on), probes=[probe])
            x = np.zeros(FS * 2, np.float32)
            x[0] = 1.0
            r.add_source(x, SRC, loop=False)
            r.add_listener(LIS)
            outs.append(r.render(1.6)[0][0].astype(np.float64))
        y = outs[0] - outs[1]
        start = int(np.argmax(np.abs(y) > 0))
        for b in (5, 6, 7):  # 1-4 kHz: enough bandwidth for a 10 dB fit on one noise tail
            fc = BANDS[b]
            sos = butter(4, [fc / np.sqrt(2), fc * np.sqrt(2)], "bandpass", fs=FS, output="sos")
            yb = sosfilt(sos, y)[start:]
            want = RT[b] * factor if on else RT[b]
            assert _edt(yb) == pytest.approx(want, rel=0.12), (on, fc, _edt(yb), want)
            assert _t30(yb) == pytest.approx(RT[b], rel=0.12), (on, fc, _t30(yb))


def test_the_late_part_of_a_sound_from_another_room_builds_up_and_keeps_its_level():
    """A source in the next room, heard through the open doorway, fills the listener's room in two parts:
    ``RenderConfig.tail_beam`` (0.7) of its late energy as 1 - e^(-t / 20 ms) (``tail_buildup``: the doorway's beam),
    the rest at the two rooms' own rate, 2 V / (c S) for these two like rooms joined by a doorway of area S. Over the
    first 20 ms after the path's arrival its late part holds several dB less than with the build-up off, the same
    energy in all (the taps' shares sum to 1: the rooms' energy balance holds), later by the build-up's mean delay
    (the energy centroid of a sum of delayed copies moves by their energy-weighted delay: 0.843 tau for each part's
    exponential cut at 3 tau); with the beam alone (``tail_beam`` 1, before session 61) from 150 ms on it is under
    1 dB above the build-up off; a source in the listener's own room is untouched. `bench fidelity` measures what it
    does against the peer."""
    from sonicverse_core.acoustics.coupling import OPENING_HEIGHT
    from sonicverse_core.acoustics.paths import path_graph
    from sonicverse_core.acoustics.probes import BakeConfig, scene_probes
    from sonicverse_core.errors import ConfigError
    from sonicverse_core.scene.spec import load_scene

    fs = 16000
    scene = load_scene("builtin:two-rooms?door=open")
    probes = scene_probes(scene, BakeConfig())
    lis = np.array([6.0, 0.6, 1.5])

    def late(src, tau, beam=0.7):
        parts = []
        for on in (True, False):
            r = AcousticRenderer(scene, RenderConfig(sample_rate=fs, output="mono", late_reverb=on, tail_buildup=tau,
                                                     tail_beam=beam), probes=probes)
            x = np.zeros(fs, np.float32)
            x[0] = 1.0
            r.add_source(x, position=src, loop=False)
            r.add_listener(lis)
            parts.append(r.render(3.0)[0].astype(np.float64).sum(0))
        return parts[0] - parts[1]

    src = np.array([2.0, 2.6, 1.2])  # the west room, out of sight
    t0 = int(round(np.hypot(path_graph(scene).path(src[:2], lis[:2]).length, 0.3) / 343.0 * fs))
    on, off, beam = late(src, 0.02), late(src, 0.0), late(src, 0.02, beam=1.0)
    e = lambda h, a, b: float(np.sum(h[t0 + int(a * fs): t0 + int(b * fs)] ** 2))  # noqa: E731
    centroid = lambda h: float(np.sum(np.arange(len(h)) * h ** 2) / np.sum(h ** 2)) / fs  # noqa: E731
    assert 10 * np.log10(e(off, 0, 0.02) / e(on, 0, 0.02)) > 3.0
    for h in (on, beam):
        assert abs(10 * np.log10(np.sum(h ** 2) / np.sum(off ** 2))) < 0.3
    slow = 2 * scene.rooms[0].volume / (343.0 * scene.doors[0].width * OPENING_HEIGHT)  # 0.15 s
    assert centroid(on) - centroid(off) == pytest.approx(0.843 * (0.7 * 0.02 + 0.3 * slow), rel=0.1)
    assert centroid(beam) - centroid(off) == pytest.approx(0.843 * 0.02, rel=0.1)
    assert 0.0 < 10 * np.log10(e(beam, 0.15, 0.6) / e(off, 0.15, 0.6)) < 1.0
    same = np.array([6.5, 3.0, 1.2])  # the listener's own room
    np.testing.assert_allclose(late(same, 0.02), late(same, 0.0), atol=1e-7)
    with pytest.raises(ConfigError, match="tail_buildup"):
        RenderConfig(tail_buildup=-0.01)
    for bad in (-0.1, 1.5, float("nan")):
        with pytest.raises(ConfigError, match="tail_beam"):
            RenderConfig(tail_beam=bad)


def test_the_tails_band_shapes_are_applied_after_an_unshaped_block():
    """A reverb's per-bin curves are rebuilt only when its groups' per-band amplitudes change (session 49). Shapes
    A, then none, then A again under a new key: the third block is shaped exactly as a fresh reverb shapes A, and a
    block with none is the plain sum."""
    from sonicverse_core.acoustics.reverb import ConvolutionReverb

    B, rt = 256, [np.full(len(BANDS), 0.4)]
    shapes = np.linspace(0.2, 2.0, 2 * len(BANDS)).reshape(2, len(BANDS))
    x = np.random.default_rng(0).normal(size=(3, 2, B)).astype(np.float32)

    def play(seq):
        rev, outs = ConvolutionReverb(FS, B, rt, groups=2), []
        for k, (sh, key) in enumerate(seq):
            outs.append(rev.process(x[k], np.ones(1), sh, out=np.zeros((2, B)), shapes_key=key))
        return outs

    got = play([(shapes, 1), (None, 2), (shapes, 3)])
    ref = play([(shapes, 1), (np.ones_like(shapes), 2), (shapes, 3)])
    for a, b in zip(got, ref):
        np.testing.assert_array_equal(a, b)
    plain = play([(None, 1)] * 3)
    assert not np.allclose(got[2], plain[2])  # the shapes do apply
