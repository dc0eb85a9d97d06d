"""Long partitions of the convolution tails (``RenderConfig.tail_partitions="auto"``, sonicverse_core/acoustics/
long_tail.py): the same convolution as one-block partitions, the work spread over the blocks, silence computing
nothing, the differences the module's docstring names measured, and its compiled kernels against their NumPy twins
(tests/test_kernels.py's twin check reads this file too)."""
import numpy as np
import pytest
from scipy.signal import butter, sosfilt

from sonicverse_core.acoustics import late_kernels as LK
from sonicverse_core.acoustics.fft import band_bins
from sonicverse_core.acoustics.reverb import ConvolutionReverb, PortalEars, long_split
from sonicverse_core.scene.materials import BANDS

FS, B = 48000, 256
RT = [np.full(len(BANDS), 1.2), np.linspace(1.5, 0.6, len(BANDS))]  # two tails: 240 blocks, long partitions of 8
_RNG = np.random.default_rng(11)
SHAPES = np.vstack([np.ones(len(BANDS)), np.linspace(0.2, 1.0, len(BANDS)), np.linspace(1.0, 0.1, len(BANDS))])


def _play(partitions, n=800, weights=None, shapes=None, ears=False, sound=lambda t: t < 300, seed=1):
    """A reverb of three groups (the third silent) fed noise while ``sound(t)``; (2, n B) output and the reverb."""
    rev = ConvolutionReverb(FS, B, RT, groups=3, partitions=partitions, direct=ears, stagger=0.3)
    e = None
    if ears:
        e = PortalEars(B)
        e.set(np.vstack([np.linspace(0.5, 1.5, 9), np.linspace(1.5, 0.5, 9)]), 0.4, band_bins(2 * B, FS).copy(),
              np.array([0, 12]))
    rng, outs = np.random.default_rng(seed), []
    for t in range(n):
        x = rng.normal(size=(3, B)).astype(np.float32) * bool(sound(t))
        x[2] = 0.0
        w = np.array([0.6, 0.4]) if weights is None else weights(t)
        out = np.zeros((2, B))
        rev.process(x, w, shapes, out=out, shapes_key=None if shapes is None else 1, ears=e)
        outs.append(out)
    return np.concatenate(outs, axis=1), rev


def _rel_db(a, b):
    return 20 * np.log10(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b ** 2)))


def test_the_split_follows_the_tails_length():
    assert long_split(30) == 0  # an environment's 0.1 s blocks: one-block partitions, its sound to the bit
    assert long_split(63) == 0 and long_split(64) == 4
    assert long_split(563) == 16  # a 3 s tail of 256-frame blocks at 48 kHz
    rev = ConvolutionReverb(FS, B, RT, partitions="uniform")
    assert rev.long is None and rev.P == 240
    rev = ConvolutionReverb(FS, B, RT)
    assert rev.m == 8 and rev.P == 16 and rev.long.Q == 28  # 16 + 8 x 28 = 240 blocks: the whole tail
    with pytest.raises(ValueError):
        ConvolutionReverb(FS, B, RT, partitions="long")
    from sonicverse_core.acoustics.config import RenderConfig
    from sonicverse_core.errors import ConfigError

    with pytest.raises(ConfigError, match="tail_partitions"):
        RenderConfig(tail_partitions="long")


@pytest.mark.parametrize("weights", [None, lambda t: np.array([0.5 + 0.5 * np.sin(t / 50), 0.5 - 0.5 * np.sin(t / 50)])],
                         ids=["fixed", "ramped"])
def test_long_partitions_are_the_same_convolution(weights):
    """Unshaped sends, both tails mixed (fixed or ramping weights), sound, then silence long enough for the long
    delay line to empty (it then computes nothing), then sound again: the output equals one-block partitions' to
    float rounding."""
    on = (lambda t: t < 300 or t > 700)
    a, _ = _play("uniform", n=900, weights=weights, sound=on)
    b, rev = _play("auto", n=900, weights=weights, sound=on)
    assert rev.long is not None and rev.long.j > rev.long.Q + 2
    assert _rel_db(b, a) < -100
    np.testing.assert_allclose(b, a, atol=1e-5 * np.abs(a).max())
    assert np.abs(a[:, 680 * B:700 * B]).max() < 1e-3 * np.abs(a).max()  # the tail had died away in the gap


def test_silence_computes_nothing_and_plays_nothing():
    """Once Q periods have passed without sound, a period transforms nothing and plays nothing (its delay line holds
    only zeros); a sound wakes it in the next period."""
    _, rev = _play("auto", n=600, sound=lambda t: t < 100)
    L = rev.long
    assert L.quiet > L.Q and np.all(L.ready == -1)
    runs = []
    for g, p in enumerate(L._fwd):
        p.run = (lambda f=p.run: runs.append(1) or f())
    x = np.zeros((3, B), np.float32)
    for _ in range(3 * L.m):
        rev.process(x, np.array([0.6, 0.4]), out=np.zeros((2, B)))
    assert not runs
    x[0] = 1.0
    for _ in range(2 * L.m):
        rev.process(x, np.array([0.6, 0.4]), out=np.zeros((2, B)))
    assert runs and L.quiet == 0


def test_each_block_does_a_share_of_the_periods_work():
    """No block transforms more than its share: each of the first F blocks of a period a 1 / F share of the live
    groups, each of the last F a 1 / F share of the inverse transforms, none both, and each block between them a
    range of the long delay line's rows (the rows covered once a period)."""
    rev = ConvolutionReverb(FS, B, RT, groups=9, direct=True)
    L = rev.long
    e = PortalEars(B)
    e.set(np.ones((2, 9)), 0.3, band_bins(2 * B, FS).copy(), np.array([3, 0]))
    count = {"fwd": 0, "inv": 0}
    for plans, kind in ((L._fwd, "fwd"), (sum(L._inv, []) + sum(L._inv_d, []), "inv")):
        for p in plans:
            p.run = (lambda f=p.run, k=kind: count.__setitem__(k, count[k] + 1) or f())
    rng = np.random.default_rng(0)
    per_block = []
    for t in range(10 * L.m):
        before = dict(count)
        rev.process(rng.normal(size=(9, B)).astype(np.float32), np.array([0.5, 0.5]), out=np.zeros((2, B)), ears=e)
        per_block.append((count["fwd"] - before["fwd"], count["inv"] - before["inv"]))
    per_block = np.array(per_block[2 * L.m:])
    assert per_block[:, 0].max() <= -(-9 // L.F) and per_block[:, 1].max() <= -(-2 * 2 // L.F)
    assert not np.any((per_block[:, 0] > 0) & (per_block[:, 1] > 0))
    assert per_block[:, 0].sum() == 9 * (len(per_block) // L.m)  # every group once a period
    assert per_block[:, 1].sum() == 4 * (len(per_block) // L.m)  # two tails, their own and directional channels
    rows = [L._work[ph] for ph in range(L.F, L.m - L.F)]
    assert rows[0][0] == 0 and rows[-1][1] == L.Q and all(a[1] == b[0] for a, b in zip(rows, rows[1:]))


def _bands(x):
    """Energy per octave band 250 Hz-4 kHz of each channel (2, 5)."""
    out = []
    for f0 in BANDS[3:8]:
        sos = butter(4, [f0 / np.sqrt(2), f0 * np.sqrt(2)], "bandpass", fs=FS, output="sos")
        out.append(np.sum(sosfilt(sos, x, axis=-1) ** 2, axis=-1))
    return np.array(out).T


@pytest.mark.parametrize("ears", [False, True], ids=["shaped", "shaped with a direction"])
def test_shaped_sends_and_a_direction_keep_every_bands_level(ears):
    """Where the sends are shaped per band (coupled rooms), the long partitions shape each period's spectrum over
    their own, finer bins, and a direction's per-ear gains likewise: the waveform differs from one-block partitions'
    by less than -45 dB, and every band's level in each ear by less than 0.02 dB."""
    a, _ = _play("uniform", shapes=SHAPES, ears=ears)
    b, _ = _play("auto", shapes=SHAPES, ears=ears)
    assert _rel_db(b, a) < -45
    np.testing.assert_allclose(10 * np.log10(_bands(b) / _bands(a)), 0.0, atol=0.02)


def test_a_tail_entering_the_mix_misses_at_most_a_decibel():
    """The worst probe change a listener makes: one of two tails at equal weights (the two nearest probes) gives way
    to a third it had not mixed in. The entering tail's part after 2 L is computed from the next period on, so for
    at most two periods the output lacks it: the level over those periods stays within 1 dB of one-block
    partitions', and equals it after."""
    rts = RT + [np.full(len(BANDS), 1.2)]
    switch = 400

    def play(partitions):
        rev = ConvolutionReverb(FS, B, rts, groups=1, partitions=partitions)
        rng, outs = np.random.default_rng(4), []
        for t in range(switch + 60):
            w = np.array([0.5, 0.5, 0.0]) if t < switch else np.array([0.5, 0.0, 0.5])
            outs.append(rev.process(rng.normal(size=(1, B)).astype(np.float32), w, out=np.zeros((2, B))))
        return np.concatenate(outs, axis=1), rev

    a, _ = play("uniform")
    b, rev = play("auto")
    m = rev.long.m
    win = slice(switch * B, (switch + 2 * m + 1) * B)
    dip = 10 * np.log10(np.sum(b[:, win] ** 2) / np.sum(a[:, win] ** 2))
    assert -1.0 < dip < 0.0
    after = slice((switch + 2 * m + 1) * B, None)
    assert _rel_db(b[:, after], a[:, after]) < -100


def test_bench_accuracy_reverb_knob_has_both_partitionings_with_the_same_decay():
    """README (bench accuracy, reverb method): the tails in long partitions decay as the one-block partitions' do
    (the same convolution); the knob's rows carry both beside the FDN."""
    from app.bench.accuracy import _reverb

    rows = {r["setting"]: r for r in _reverb(quick=True)["rows"]}
    assert set(rows) == {"fdn", "convolution", "convolution uniform"}
    np.testing.assert_allclose(rows["convolution"]["rt60_measured"], rows["convolution uniform"]["rt60_measured"],
                               atol=1e-3)
    assert rows["convolution"]["error"] < 0.1


def test_the_longest_tail_at_the_finest_blocks():
    """An extreme a user can ask for: an 8 s tail (the synthesis' cap; RT60 up to 60 s) at 96 kHz in 64-frame blocks
    is 12,000 partitions: long partitions of 64 blocks (the cap), 16 blocks transforming each period. The same
    output as one-block partitions, finite, with the same energy in both ears."""
    rt = [np.full(len(BANDS), 60.0)]
    fs, b, n = 96_000, 64, 420
    outs = []
    for partitions in ("uniform", "auto"):
        rev = ConvolutionReverb(fs, b, rt, seconds=8.0, partitions=partitions)
        rng, y = np.random.default_rng(2), []
        for t in range(n):
            y.append(rev.process(rng.normal(size=(1, b)).astype(np.float32) * (t < 100), np.ones(1),
                                 out=np.zeros((2, b))))
        outs.append(np.concatenate(y, axis=1))
    assert rev.m == 64 and rev.long.F == 16 and rev.long.Q == 186
    a, c = outs
    assert np.all(np.isfinite(c)) and np.abs(c[:, 2 * 64 * b:]).max() > 0  # the long partitions play
    assert _rel_db(c, a) < -100
    e = np.sum(c[:, 2 * 64 * b:] ** 2, axis=1)
    assert abs(10 * np.log10(e[0] / e[1])) < 1.0


def test_listeners_transform_in_other_blocks_and_hear_the_same():
    """Listeners rendered in one callback (robots) do their long partitions' transforms in other blocks of the period
    (their reverbs are staggered by the golden section); two listeners at the same place still hear the same."""
    from sonicverse_core.acoustics.probes import Probe
    from sonicverse_core.acoustics.renderer import AcousticRenderer, RenderConfig

    dims = np.array([8.0, 6.0, 3.0])
    probe = Probe(dims / 2, np.full(9, 1.2), np.full(9, 1.2), np.zeros(3), dims, ("PlasterRough",) * 6, 1.0)
    r = AcousticRenderer(None, RenderConfig(occlusion=False, early_reflections=False), probes=[probe])
    r.add_source(np.random.default_rng(0).normal(size=48000).astype(np.float32) * 0.1, (2.0, 2.0, 1.5))
    for _ in range(3):
        r.add_listener((5.0, 4.0, 1.5))
    out = [[], [], []]
    for _ in range(300):
        for k, y in enumerate(r.render_block()):
            out[k].append(y)
    phases = [st.late.conv.long.phase for st in r._state]
    assert len(set(phases)) == 3, phases
    a, b, c = (np.concatenate(o, axis=1).astype(np.float64) for o in out)
    assert _rel_db(b, a) < -100 and _rel_db(c, a) < -100


def test_fdl_mac_add():
    """A range of the delay line's rows, added into what the output holds (a long partition's share of a period)."""
    P, F = 7, 17
    fdl = (_RNG.normal(size=(P, F)) + 1j * _RNG.normal(size=(P, F))).astype(np.complex64)
    H = (_RNG.normal(size=(2 * P, 2, F)) + 1j * _RNG.normal(size=(2 * P, 2, F))).astype(np.complex64)
    start = (_RNG.normal(size=(2, F)) + 1j * _RNG.normal(size=(2, F))).astype(np.complex64)
    out = start.copy()
    LK.fdl_mac_add(fdl, H, 3, 2, 5, out)
    np.testing.assert_allclose(out, start + np.einsum("pf,pef->ef", fdl[2:5], H[5:8]), rtol=1e-4, atol=1e-4)
    whole = np.zeros((2, F), np.complex64)
    for a, b in ((0, 3), (3, 3), (3, 7)):  # in shares, the whole
        LK.fdl_mac_add(fdl, H, 3, a, b, whole)
    ref = np.empty((2, F), np.complex64)
    LK.fdl_mac(fdl, H, 3, ref)
    np.testing.assert_allclose(whole, ref, rtol=1e-5, atol=1e-5)


def test_long_close_take_play_and_pick_slots():
    G, L = 5, 8
    frame = _RNG.normal(size=(G, 2 * L)).astype(np.float32)
    col = _RNG.normal(size=(G, L)).astype(np.float32)
    last = np.array([True, False, True, False, False])
    this = np.array([True, True, False, False, False])
    want = frame.copy()
    for g in range(G):
        if last[g] or this[g]:
            want[g, :L] = frame[g, L:] if last[g] else 0.0
            want[g, L:] = col[g]
    live, order = np.zeros(G, bool), np.full(G, -1, np.int64)
    n = LK.long_close(frame, col, last, this, live, order)
    assert n == 3 and list(order[:n]) == [0, 1, 2] and list(live) == [True, True, True, False, False]
    np.testing.assert_array_equal(frame, want)
    assert list(last) == [True, True, False, False, False] and not this.any()
    flags = np.array([True, False, False])
    x = _RNG.normal(size=(3, 4)).astype(np.float32)
    col3 = np.zeros((3, 12), np.float32)
    LK.long_take(x, col3, 4, np.array([False, True, False]), flags)
    assert list(flags) == [True, True, False]
    np.testing.assert_array_equal(col3[:, 4:8], x)
    assert not col3[:, :4].any() and not col3[:, 8:].any()
    S, E, Lh, B = 3, 2, 16, 4
    y = _RNG.normal(size=(2, S, E, Lh)).astype(np.float32)
    ready, a, b = np.array([2, -1, 0]), np.array([0.5, 0.0, 0.2]), np.array([0.3, 0.9, 1e-5])
    out = _RNG.normal(size=(E, B))
    want = out.copy()
    for s in range(S):
        k = ready[s]
        if k >= 0 and (a[k] > 1e-4 or b[k] > 1e-4):
            want += 0.1 * y[1, s, :, 9:9 + B] * (a[k] + (b[k] - a[k]) * (np.arange(B) + 1) / B) * \
                (1.0 + (0.5 - 1.0) * (np.arange(B) + 1) / B)
    LK.long_play(y, 1, 9, ready, a, b, 1.0, 0.5, 0.1, out)
    np.testing.assert_allclose(out, want, rtol=1e-6)
    w0, w1 = np.array([0.0, 0.3, 0.0, 0.9, 1e-5]), np.array([0.0, 0.2, 0.5, 0.0, 1e-5])
    slots = np.empty(4, np.int64)
    LK.pick_slots(w0, w1, slots)
    assert list(slots) == [3, 2, 1, -1]  # by max(w0, w1), none at or below 1e-4
    LK.pick_slots(w0, w1, slots[:2])
    assert list(slots[:2]) == [3, 2]
