"""The procedural sound bank: one recognisable sound family per sounding category (15), 4 variants each.

Variants 0-2 are the *heard* set (training and heard-sound tests), variant 3 the *unheard* set. Sounds are
non-periodic and discontinuous: events of a category-specific timbre at random times with random gaps, 2-5 s
long. Everything is deterministic per (category, variant). Mono float32 at 48 kHz, peak 0.5.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy import signal

from sonicverse_core.errors import AssetError

SAMPLE_RATE = 48_000
CATEGORIES = ("straight_chair", "breakfast_table", "picture", "bottom_cabinet", "cushion", "sofa", "bed", "shelf",
              "sink", "toilet", "stool", "standing_tv", "shower", "bathtub", "countertop")
VARIANTS = 4
HEARD = (0, 1, 2)
UNHEARD = (3,)


def _env(n, attack, decay, sr):
    t = np.arange(n) / sr
    return np.minimum(1.0, t / max(attack, 1e-4)) * np.exp(-t / max(decay, 1e-4))


def _modes(rng, sr, freqs, decay, dur):
    n = int(dur * sr)
    t = np.arange(n) / sr
    out = np.zeros(n)
    for f in freqs:
        f = f * rng.uniform(0.97, 1.03)
        out += rng.uniform(0.4, 1.0) * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi)) * np.exp(-t / decay)
    return out


def _noise(rng, n):
    return rng.standard_normal(n)


def _band(x, lo, hi, sr, order=2):
    hi = min(hi, 0.45 * sr)
    sos = signal.butter(order, [lo, hi], btype="band", fs=sr, output="sos")
    return signal.sosfilt(sos, x)


def _event(cat: str, rng: np.random.Generator, sr: int, k: float) -> np.ndarray:
    """One event of a category's timbre; k in [0.8, 1.25] shifts the variant's pitch/size."""
    if cat == "straight_chair":  # creak: rough, jittered tone
        dur = rng.uniform(0.25, 0.5)
        n = int(dur * sr)
        f = 420 * k * (1 + 0.15 * np.cumsum(rng.standard_normal(n)) / np.sqrt(n))
        ph = 2 * np.pi * np.cumsum(f) / sr
        return signal.sawtooth(ph) * (0.6 + 0.4 * rng.random(n)) * _env(n, 0.02, dur / 2, sr)
    if cat == "breakfast_table":  # knock on wood
        return _modes(rng, sr, [180 * k, 410 * k, 730 * k], 0.035, 0.25)
    if cat == "picture":  # tap on a framed glass
        return _modes(rng, sr, [2100 * k, 3300 * k, 4700 * k], 0.02, 0.15)
    if cat == "bottom_cabinet":  # cabinet door shut: thump + click
        x = _modes(rng, sr, [85 * k, 140 * k], 0.06, 0.3)
        x[: int(0.004 * sr)] += _noise(rng, int(0.004 * sr)) * 0.8
        return x
    if cat == "cushion":  # soft pat
        n = int(rng.uniform(0.08, 0.15) * sr)
        return _band(_noise(rng, n), 80, 600 * k, sr) * _env(n, 0.005, 0.04, sr) * 3
    if cat == "sofa":  # fabric rustle
        n = int(rng.uniform(0.4, 0.9) * sr)
        am = 0.5 + 0.5 * np.abs(np.sin(np.linspace(0, rng.uniform(6, 14), n)))
        return _band(_noise(rng, n), 500 * k, 2500 * k, sr) * am * np.hanning(n) * 2
    if cat == "bed":  # spring squeak: fm tone
        dur = rng.uniform(0.15, 0.3)
        n = int(dur * sr)
        t = np.arange(n) / sr
        f = 900 * k + 250 * np.sin(2 * np.pi * 6 * t)
        return np.sin(2 * np.pi * np.cumsum(f) / sr) * np.hanning(n)
    if cat == "shelf":  # rattle: burst of clicks
        n = int(rng.uniform(0.15, 0.35) * sr)
        x = np.zeros(n)
        for i in rng.integers(0, n - 200, rng.integers(6, 14)):
            x[i:i + 200] += _modes(rng, sr, [1500 * k, 2600 * k], 0.002, 200 / sr)
        return x
    if cat == "sink":  # drip: rising bloop
        n = int(0.04 * sr)
        t = np.arange(n) / sr
        f = 900 * k * (1 + 25 * t)
        return np.sin(2 * np.pi * np.cumsum(f) / sr) * _env(n, 0.002, 0.012, sr)
    if cat == "toilet":  # flush: noise with a falling low-pass
        n = int(rng.uniform(1.2, 2.0) * sr)
        x = _noise(rng, n)
        out = np.zeros(n)
        for i, s in enumerate(range(0, n, 4800)):
            sos = signal.butter(2, max(300.0, 3000 * k * (1 - i * 4800 / n)), fs=sr, output="sos")
            out[s:s + 4800] = signal.sosfilt(sos, x[s:s + 4800])
        return out * np.hanning(n) * 2
    if cat == "stool":  # scrape on the floor: moving resonance
        n = int(rng.uniform(0.3, 0.6) * sr)
        f0 = 300 * k + 500 * k * rng.random()
        b, a = signal.iirpeak(f0, 8, fs=sr)
        return signal.lfilter(b, a, _noise(rng, n)) * np.hanning(n) * 2
    if cat == "standing_tv":  # tv: formant-ish voiced syllables
        n = int(rng.uniform(0.15, 0.3) * sr)
        t = np.arange(n) / sr
        f0 = 140 * k * (1 + 0.1 * np.sin(2 * np.pi * 5 * t))
        src = signal.sawtooth(2 * np.pi * np.cumsum(f0) / sr)
        return (_band(src, 500, 900, sr) + 0.6 * _band(src, 1400, 2200, sr)) * np.hanning(n) * 3
    if cat == "shower":  # hiss
        n = int(rng.uniform(1.0, 2.0) * sr)
        return _band(_noise(rng, n), 2000 * k, 12000, sr) * np.hanning(n)
    if cat == "bathtub":  # splash
        n = int(rng.uniform(0.2, 0.4) * sr)
        return _band(_noise(rng, n), 200, 1800 * k, sr) * _env(n, 0.01, 0.08, sr) * 2
    if cat == "countertop":  # chopping
        n = int(0.06 * sr)
        x = _modes(rng, sr, [600 * k, 1150 * k, 2400 * k], 0.01, 0.06)
        x[:48] += _noise(rng, 48)
        return x
    raise AssetError(f"no sound recipe for category '{cat}'")  # pragma: no cover


@lru_cache(maxsize=128)
def _sound(cat: str, variant: int) -> np.ndarray:
    seed = [CATEGORIES.index(cat), variant, 0x50D]
    rng = np.random.default_rng(seed)
    sr = SAMPLE_RATE
    k = (0.8, 1.0, 1.12, 1.25)[variant]
    total = int(rng.uniform(2.0, 5.0) * sr)
    out = np.zeros(total)
    t = int(rng.uniform(0.0, 0.2) * sr)
    while t < total:
        ev = _event(cat, rng, sr, k)
        ev = ev / (np.max(np.abs(ev)) + 1e-12) * rng.uniform(0.5, 1.0)
        end = min(total, t + len(ev))
        out[t:end] += ev[: end - t]
        # random gap: non-periodic, sometimes long silences
        t = end + int(rng.exponential(0.25 if cat not in ("toilet", "shower") else 0.6) * sr)
    fade = min(total, 480)
    out[-fade:] *= np.linspace(1, 0, fade)
    out = out / (np.max(np.abs(out)) + 1e-12) * 0.5
    res = out.astype(np.float32)
    res.setflags(write=False)
    return res


def sound(category: str, variant: int = 0) -> np.ndarray:
    """(n,) float32 mono sound at :data:`SAMPLE_RATE` for a category and variant (0..3); read-only."""
    if category not in CATEGORIES:
        raise AssetError(f"no built-in sound for '{category}'; categories: {', '.join(CATEGORIES)}")
    if not 0 <= variant < VARIANTS:
        raise AssetError(f"sound variant must be 0..{VARIANTS - 1}, got {variant}")
    return _sound(category, variant)


def sound_names(split: str = "all") -> list[str]:
    """Names 'category/variant' in a split: 'heard', 'unheard' or 'all'."""
    variants = {"heard": HEARD, "unheard": UNHEARD, "all": tuple(range(VARIANTS))}.get(split)
    if variants is None:
        raise AssetError(f"unknown sound split '{split}'; use heard, unheard or all")
    return [f"{c}/{v}" for c in CATEGORIES for v in variants]


def by_name(name: str) -> np.ndarray:
    """'sofa/2' or 'sofa' (variant 0)."""
    cat, _, var = name.partition("/")
    try:
        v = int(var) if var else 0
    except ValueError:
        raise AssetError(f"bad sound name '{name}': write CATEGORY or CATEGORY/VARIANT") from None
    return sound(cat, v)


def pcm_sha256(x: np.ndarray) -> str:
    """Hash of the 16-bit PCM quantisation (stable across platforms' last-bit float differences)."""
    from assets_manifest import sha256_bytes

    return sha256_bytes(np.round(np.asarray(x, np.float64) * 32767).astype("<i2").tobytes())


def load_sound(name: str) -> tuple[np.ndarray, int]:
    """A sound bank name ('sofa', 'sofa/2') or a WAV/FLAC file -> (mono float32 signal, its sample rate)."""
    from pathlib import Path

    if "/" in name and not Path(name).suffix or name.split("/")[0] in CATEGORIES and not Path(name).exists():
        return by_name(name), SAMPLE_RATE
    p = Path(name)
    if not p.is_file():
        raise AssetError(f"sound not found: '{name}' is neither a file nor a sound bank name "
                         f"({', '.join(CATEGORIES)})")
    import soundfile as sf

    try:
        x, sr = sf.read(str(p), dtype="float32", always_2d=True)
    except Exception as exc:  # noqa: BLE001 - libsndfile's errors come in several types
        raise AssetError(f"cannot read sound file {p}: {exc}") from None
    if x.size == 0:
        raise AssetError(f"sound file {p} holds no samples")
    bad = int(np.count_nonzero(~np.isfinite(x)))
    if bad:
        raise AssetError(f"sound file {p} has {bad} NaN or infinite samples (a float WAV written by a broken "
                         f"program?): fix or re-export it")
    return x.mean(axis=1), sr
