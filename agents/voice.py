"""Spoken-command recogniser for voice-driven retrieval: which object the person asks for, from what reaches the
robot's ears.

A small keyword classifier (torch; 1-D convolutions over log-mel frames, mean and max pooled over time) maps one
utterance to one of the home's object categories or ``other`` (any phrase that is not a command). It is trained on
synthetic speech only, made robust to the voice, the room and the distance by what it is trained on:

* espeak-ng speech of every command template x object name (and the person's other phrases as ``other``) in the
  accents of ``ACCENTS`` x the voice variants of ``TRAIN_VARIANTS``, at random speeds (120-190 wpm) and pitches;
* each presentation convolved with a random room response (a direct impulse and an exponentially decaying noise
  tail: RT60 0.2-1.2 s, direct-to-reverberant ratio -12..+12 dB, so also the next room through a door) and mixed
  with noise at 0-30 dB SNR, gain and a random start offset;
* features: 40 log-mel bands at 16 kHz (25 ms windows, 10 ms hop) floored 70 dB under the utterance's loudest band,
  each band's mean over the utterance removed (a gain, and a room's or a microphone's colouring that is flat within
  a band, are constant offsets in log-mel).

The person's voices (``sonicverse_core.world.person.VOICES``: the default, ``+f2`` and ``+m3`` variants) are held
out: no training utterance uses those variants, so the accuracies measured on them (``sonicverse bench recogniser``)
are on voices it was not trained on. The weights ship with the project (``agents/data/voice_commands.pt``, made
by ``sonicverse task train-recogniser``, seeded); nothing is downloaded at run time. At inference a caller may
restrict the answer to the objects its scene holds (``allowed``), as a grammar would.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sonicverse_core.errors import AssetError, ConfigError
from sonicverse_core.tasks.retrieval import SPOKEN, TEMPLATES  # the task's vocabulary
from sonicverse_core.world.person import PHRASES

log = logging.getLogger(__name__)

SAMPLE_RATE = 16_000
N_MELS = 40
CLASSES = tuple(SPOKEN) + ("other",)
#: phrases that are not commands: the person's (the same tuple, so training and the tasks never drift apart), a few more
OTHER = PHRASES + ("thank you", "hello robot", "wait for me", "bring it here", "put it down", "where are you")
ACCENTS = ("en-us", "en-gb", "en-gb-scotland", "en-gb-x-gbclan", "en-gb-x-rp", "en-gb-x-gbcwmd", "en-029",
           "en-us-nyc")
#: espeak-ng voice variants used for training (the person's variants, none / f2 / m3, are held out)
TRAIN_VARIANTS = ("f1", "f3", "f4", "f5", "m1", "m2", "m4", "m5", "m6", "m7", "m8", "klatt", "klatt2", "klatt3",
                  "Alex", "Annie", "Andy", "adam", "anika", "aunty", "belinda", "benjamin", "boris", "caleb", "david",
                  "ed", "edward", "grandma", "grandpa", "iven", "john", "linda", "max", "michel", "norbert", "paul",
                  "robert", "steph", "travis", "victor", "zac", "Mike", "Lee", "Jacky", "Hugo", "Denis")
WEIGHTS = Path(__file__).parent / "data" / "voice_commands.pt"


def command_text(category: str, template: int = 0) -> str:
    """The spoken command asking for ``category``."""
    if category not in SPOKEN:
        raise ConfigError(f"no spoken name for '{category}'")
    return TEMPLATES[template % len(TEMPLATES)].format(SPOKEN[category])


# --- features ------------------------------------------------------------------------------------------------------
def _mel_matrix(n_fft: int = 512, sr: int = SAMPLE_RATE, n_mels: int = N_MELS) -> np.ndarray:
    """Triangular mel filters (HTK mel scale) (n_mels, n_fft // 2 + 1), 60 Hz - 7.6 kHz."""
    mel = lambda f: 2595 * np.log10(1 + f / 700)  # noqa: E731
    inv = lambda m: 700 * (10 ** (m / 2595) - 1)  # noqa: E731
    edges = inv(np.linspace(mel(60.0), mel(7600.0), n_mels + 2))
    f = np.fft.rfftfreq(n_fft, 1 / sr)
    lo, c, hi = edges[:-2, None], edges[1:-1, None], edges[2:, None]
    return np.maximum(0, np.minimum((f - lo) / (c - lo), (hi - f) / (hi - c))).astype(np.float32)


_MEL = _mel_matrix()
_WIN = np.hanning(400).astype(np.float32)


def features(x: np.ndarray, sample_rate: int = SAMPLE_RATE) -> np.ndarray:
    """Log-mel frames (frames, 40) float32 of mono ``x``, each band's mean removed; resampled to 16 kHz first."""
    x = np.asarray(x, np.float32).ravel()
    if not np.all(np.isfinite(x)):
        raise ConfigError("speech samples must be finite")
    if sample_rate != SAMPLE_RATE:
        from scipy.signal import resample_poly

        g = np.gcd(int(sample_rate), SAMPLE_RATE)
        x = resample_poly(x, SAMPLE_RATE // g, int(sample_rate) // g).astype(np.float32)
    if len(x) < 400:
        x = np.pad(x, (0, 400 - len(x)))
    n = 1 + (len(x) - 400) // 160
    frames = np.lib.stride_tricks.as_strided(x, (n, 400), (x.strides[0] * 160, x.strides[0])) * _WIN
    p = np.abs(np.fft.rfft(frames, 512, axis=1)) ** 2
    m = p @ _MEL.T
    f = np.log(m + 1e-7 * max(float(m.max()), 1e-30))  # a floor 70 dB under the loudest band: gain-invariant
    return (f - f.mean(0)).astype(np.float32)


# --- the model ----------------------------------------------------------------------------------------------------
def _model(n_classes: int = len(CLASSES), width: int = 64):
    import torch.nn as nn

    class KeywordNet(nn.Module):
        def __init__(self):
            super().__init__()
            self.conv = nn.Sequential(
                nn.Conv1d(N_MELS, width, 5, padding=2), nn.BatchNorm1d(width), nn.ReLU(),
                nn.Conv1d(width, width, 5, padding=4, dilation=2), nn.BatchNorm1d(width), nn.ReLU(),
                nn.Conv1d(width, width, 5, padding=8, dilation=4), nn.BatchNorm1d(width), nn.ReLU(),
                nn.Conv1d(width, width, 5, padding=16, dilation=8), nn.BatchNorm1d(width), nn.ReLU())
            self.head = nn.Linear(2 * width, n_classes)

        def forward(self, x, mask):  # x (batch, 40, T), mask (batch, 1, T) 1 on real frames
            h = self.conv(x)
            mean = (h * mask).sum(-1) / mask.sum(-1).clamp(min=1)
            mx = (h - 1e4 * (1 - mask)).amax(-1)
            import torch

            return self.head(torch.cat([mean, mx], 1))

    return KeywordNet()


def _batch(feats: list[np.ndarray]):
    import torch

    T = max(len(f) for f in feats)
    x = np.zeros((len(feats), N_MELS, T), np.float32)
    m = np.zeros((len(feats), 1, T), np.float32)
    for i, f in enumerate(feats):
        x[i, :, : len(f)] = f.T
        m[i, :, : len(f)] = 1
    return torch.from_numpy(x), torch.from_numpy(m)


@dataclass
class Recognition:
    category: str  # an object category, or "other"
    confidence: float  # its posterior probability


class CommandRecogniser:
    """The trained keyword classifier (CPU)."""

    def __init__(self, weights: Path | str = WEIGHTS):
        import torch

        path = Path(weights)
        if not path.is_file():
            raise AssetError(f"recogniser weights not found: {path} (make them with `sonicverse task "
                             "train-recogniser`)")
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:  # noqa: BLE001 - torch's errors for a broken file come in several types
            raise AssetError(f"cannot read recogniser weights {path}: {exc}") from None
        self.net = _model()
        try:
            self.net.load_state_dict({k: v.float() for k, v in state.items()})
        except (RuntimeError, KeyError) as exc:
            raise AssetError(f"recogniser weights {path} do not fit the model: {exc}") from None
        self.net.eval()

    def posteriors(self, x: np.ndarray, sample_rate: int) -> np.ndarray:
        """Class probabilities (len(CLASSES),) of one utterance."""
        import torch

        with torch.no_grad():
            logits = self.net(*_batch([features(x, sample_rate)]))[0]
        return torch.softmax(logits, 0).numpy()

    def recognise(self, x: np.ndarray, sample_rate: int, allowed=None) -> Recognition:
        """The category asked for (restricted to ``allowed`` categories plus ``other`` when given)."""
        p = self.posteriors(x, sample_rate)
        if allowed is not None:
            bad = [c for c in allowed if c not in SPOKEN]
            if bad:
                raise ConfigError(f"unknown categories {bad}")
            keep = np.array([c in allowed or c == "other" for c in CLASSES])
            p = np.where(keep, p, 0.0)
            p = p / max(p.sum(), 1e-12)
        k = int(np.argmax(p))
        return Recognition(CLASSES[k], float(p[k]))


# --- training -----------------------------------------------------------------------------------------------------
def _room_response(rng: np.random.Generator) -> np.ndarray:
    """A random room response at 16 kHz: a direct impulse and an exponentially decaying noise tail."""
    rt = rng.uniform(0.2, 1.2)
    n = int(min(rt, 1.0) * SAMPLE_RATE)
    t = np.arange(n) / SAMPLE_RATE
    tail = rng.normal(size=n) * np.exp(-6.9 * t / rt)
    onset = int(rng.uniform(0.002, 0.02) * SAMPLE_RATE)
    tail[:onset] = 0
    drr = rng.uniform(-12, 12)
    tail *= np.sqrt(10 ** (-drr / 10) / max(np.sum(tail ** 2), 1e-12))
    if rng.uniform() < 0.5:  # a duller room: high frequencies decay faster
        from scipy.signal import lfilter

        a = rng.uniform(0.3, 0.8)
        tail = lfilter([1 - a], [1, -a], tail)
    tail[0] += 1.0
    return tail.astype(np.float32)


def _augment(x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    from scipy.signal import fftconvolve

    y = fftconvolve(x, _room_response(rng))[: len(x) + SAMPLE_RATE // 4]
    y = np.concatenate([np.zeros(int(rng.uniform(0, 0.3) * SAMPLE_RATE)), y])
    p = np.mean(y ** 2) + 1e-12
    snr = rng.uniform(0, 30)
    noise = rng.normal(size=len(y))
    if rng.uniform() < 0.5:  # pink-ish
        noise = np.cumsum(noise) * 0.02
        noise -= np.convolve(noise, np.ones(200) / 200, "same")
    y = y + noise * np.sqrt(p / (10 ** (snr / 10)) / max(np.mean(noise ** 2), 1e-12))
    return (y * rng.uniform(0.1, 1.0) / max(np.abs(y).max(), 1e-9)).astype(np.float32)


def training_set(rng: np.random.Generator, per_class: int = 160, progress=None):
    """(signals at 16 kHz, labels) of synthetic utterances in the training voices."""
    from assets_manifest.speech import speak

    xs, ys = [], []
    jobs = []
    for k, c in enumerate(CLASSES):
        for _ in range(per_class):
            text = (OTHER[int(rng.integers(len(OTHER)))] if c == "other" else
                    TEMPLATES[int(rng.integers(len(TEMPLATES)))].format(SPOKEN[c]))
            voice = f"{ACCENTS[int(rng.integers(len(ACCENTS)))]}+{TRAIN_VARIANTS[int(rng.integers(len(TRAIN_VARIANTS)))]}"
            jobs.append((text, voice, int(rng.integers(120, 191)), int(rng.integers(20, 81)), k))
    for i, (text, voice, speed, pitch, k) in enumerate(jobs):
        x, _ = speak(text, voice=voice, speed=speed, pitch=pitch, pad_s=0.05, sample_rate=SAMPLE_RATE)
        xs.append(x)
        ys.append(k)
        if progress is not None:
            progress(i + 1, len(jobs))
    return xs, np.array(ys)


def train(seed: int = 0, epochs: int = 24, per_class: int = 160, out: Path | str = WEIGHTS, progress=None) -> dict:
    """Train the recogniser from scratch (seeded) and save its weights (float16); returns a summary."""
    import torch

    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    xs, ys = training_set(rng, per_class, progress)
    net = _model()
    opt = torch.optim.AdamW(net.parameters(), lr=3e-3, weight_decay=1e-3)
    steps = epochs * int(np.ceil(len(xs) / 64))
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=3e-3, total_steps=steps)
    loss_fn = torch.nn.CrossEntropyLoss(label_smoothing=0.05)
    history = []
    for ep in range(epochs):
        net.train()
        order = rng.permutation(len(xs))
        total, correct = 0.0, 0
        for b in range(0, len(order), 64):
            idx = order[b:b + 64]
            x, m = _batch([features(_augment(xs[i], rng)) for i in idx])
            y = torch.from_numpy(ys[idx])
            logits = net(x, m)
            loss = loss_fn(logits, y)
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            total += loss.item() * len(idx)
            correct += int((logits.argmax(1) == y).sum())
        history.append({"epoch": ep + 1, "loss": total / len(xs), "train_accuracy": correct / len(xs)})
        log.info("epoch %d: loss %.3f, accuracy %.3f", ep + 1, history[-1]["loss"], history[-1]["train_accuracy"])
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    torch.save({k: v.half() if v.is_floating_point() else v for k, v in net.state_dict().items()}, tmp)
    tmp.replace(out)
    return {"utterances": len(xs), "epochs": epochs, "seed": seed, "weights": str(out),
            "parameters": sum(p.numel() for p in net.parameters()), "history": history}
