"""A learned sound localiser: where the sounding object is from the robot, heard in one step.

Gan et al. (2020, "Look, listen, and act") navigate to a sound by *predicting* the goal's position from the audio
with a network trained on labelled recordings, mapping free space from depth, and planning to the prediction; the
``gan`` agent (:class:`agents.scripted.GanAgent`) does the same with this model. (The hand-made estimator before it,
interaural delays triangulated over spins in place, is kept as ``gan-itd``: in reverberant homes its estimates were
metres off.)

Input: the binaural spectrogram (2 x 64 x 49, the last second) and the GCC-PHAT interaural cross-correlation of the
last step's audio over lags of +-0.75 ms (the delay cue the spectrogram's magnitudes lose). Output: cosine and sine
of the object's bearing from the robot's heading and log(1 + distance in m). Where the cues cannot tell front from
back the regression shrinks the (cos, sin) vector, so its length is the estimate's confidence.

Training (:func:`train`): frames from train homes with heard sounds, heard from places along the way to the sound at
random headings (:func:`collect`), labelled with the object's true position; only frames in which the sound is
audible. Validation on
val homes: the median bearing error and the distance error.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from agents.models import SPEC_MAX, _cnn

ITD_MAX = 0.00075  # s: lags of the cross-correlation input (the head's largest delay 0.66 ms, and a margin)
SENSORS = ("audio", "spectrogram", "pose")


@dataclass(frozen=True)
class LocalizerConfig:
    spec_shape: tuple = (2, 64, 49)
    lags: int = 27  # 2 * ceil(ITD_MAX * 16 kHz) + 1 + 2
    hidden: int = 128


def gcc_input(audio: np.ndarray, sr: int) -> np.ndarray:
    """The cross-correlation input: GCC-PHAT over lags -L..L of the step's binaural audio (zeros when silent)."""
    from agents.scripted import gcc_phat

    cc, _ = gcc_phat(audio, sr, ITD_MAX)
    return cc.astype(np.float32)


def audible(audio: np.ndarray) -> bool:
    return float(np.mean(np.asarray(audio, np.float64) ** 2)) > 1e-9


class SoundLocalizer(nn.Module):
    def __init__(self, cfg: LocalizerConfig = LocalizerConfig()):
        super().__init__()
        self.cfg = cfg
        h = cfg.hidden
        self.spec = _cnn(cfg.spec_shape[0], cfg.spec_shape[1:], h, k=(5, 3, 3), s=(2, 2, 1))
        self.gcc = nn.Sequential(nn.Linear(cfg.lags, 64), nn.ReLU())
        self.out = nn.Sequential(nn.Linear(h + 64, h), nn.ReLU(), nn.Linear(h, 3))

    def forward(self, spec: torch.Tensor, gcc: torch.Tensor) -> torch.Tensor:
        """``spec`` (B, 2, F, T) log-magnitudes, ``gcc`` (B, lags) -> (B, 3): cos, sin of the bearing, log1p(m)."""
        s = (spec.float() / SPEC_MAX).clamp(0, 1)
        return self.out(torch.cat([self.spec(s), self.gcc(gcc.float())], 1))

    def predict(self, spectrogram: np.ndarray, audio: np.ndarray, sr: int) -> np.ndarray:
        """One step's estimate (cos, sin, log1p distance) from the observation's spectrogram and audio."""
        with torch.no_grad():
            y = self(torch.from_numpy(np.asarray(spectrogram, np.float32))[None],
                     torch.from_numpy(gcc_input(audio, sr))[None])
        return y[0].numpy()


def target(env) -> np.ndarray:
    """The label: where the episode's sounding object (the centre of its box) is from the robot."""
    w = env.home.world
    c = w.scene.object(env.episode.object_name).world_bounds()[:, :2].mean(0)
    d = c - w.pose[:2]
    b = math.atan2(d[1], d[0]) - math.radians(w.pose[2])
    return np.array([math.cos(b), math.sin(b), math.log1p(math.hypot(*d))], np.float32)


@dataclass
class LocalizerTrainConfig:
    task: str = "SemanticAudioNav"
    frames: int = 20_000  # audible training frames to collect
    val_frames: int = 2_000
    epochs: int = 12
    batch: int = 64
    lr: float = 1e-3
    seed: int = 0
    turn_prob: float = 0.5  # the share of recordings made while turning on the spot
    episode_steps: int = 150


def collect(task: str, split: str, frames: int, rng: np.random.Generator, turn_prob: float = 0.5,
            episode_steps: int = 150, progress=None) -> dict:
    """``frames`` audible frames of (spectrogram quantised to uint8, GCC-PHAT, label) from ``split`` homes.

    The robot's heading is uncorrelated with where the sound is: in each episode it stands at a few places along
    the shortest path to the sound, turned to a uniformly random heading, waits ``WAIT`` steps (the spectrogram's
    second fills with audio heard there), then records ``RECORD`` frames, standing or turning on the spot (share
    ``turn_prob``: the agent hears while it turns). Driven by the oracle alone, the sound would nearly always be
    ahead, and a model learns to answer "ahead"."""
    from agents.imitation import Expert, _quantise
    from sonicverse_core.tasks import make_env

    WAIT, RECORD, DRIVE = 10, 6, 12
    env = make_env(task, split=split, sensors=SENSORS)
    sr = env.cfg.sample_rate
    expert = Expert()
    out = {"s": [], "c": [], "y": []}
    still = np.zeros(env.action_space.shape, np.float32)
    if len(still) == 3:
        still[2] = -1.0
    try:
        while len(out["y"]) < frames:
            obs, info = env.reset(seed=int(rng.integers(2**31)))
            expert.reset(env, obs, info)
            steps, done = 0, False
            while not done and steps < episode_steps and len(out["y"]) < frames:
                w = env.home.world
                w.place_robot(w.pose[0], w.pose[1], float(rng.uniform(-180.0, 180.0)))
                turn = still.copy()
                if rng.random() < turn_prob:
                    turn[:2] = (-0.5, 0.5) if rng.random() < 0.5 else (0.5, -0.5)
                for k in range(WAIT + RECORD):
                    if k >= WAIT and audible(obs["audio"]):
                        out["s"].append(_quantise(obs)[1])
                        out["c"].append(gcc_input(obs["audio"], sr))
                        out["y"].append(target(env))
                    obs, _, term, trunc, info = env.step(still if k < WAIT else turn)
                    steps += 1
                    done = term or trunc
                    if done:
                        break
                expert.reset(env, obs, info)  # replan from the new heading, then drive on
                for _ in range(DRIVE):
                    if done:
                        break
                    obs, _, term, trunc, info = env.step(np.asarray(expert.label(obs, info), np.float32))
                    steps += 1
                    done = term or trunc
            if progress is not None:
                progress(len(out["y"]))
    finally:
        env.close()
    return {k: np.stack(v)[:frames] for k, v in out.items()}


def errors(model: SoundLocalizer, data: dict) -> dict:
    """Median and 90th-percentile bearing error (degrees) and median distance error (m) of ``model`` on ``data``."""
    with torch.no_grad():
        y = torch.cat([model(torch.from_numpy(data["s"][i:i + 512]).float() * (SPEC_MAX / 255),
                             torch.from_numpy(data["c"][i:i + 512])) for i in range(0, len(data["y"]), 512)]).numpy()
    t = data["y"]
    db = np.degrees(np.abs((np.arctan2(y[:, 1], y[:, 0]) - np.arctan2(t[:, 1], t[:, 0]) + np.pi) % (2 * np.pi)
                           - np.pi))
    dd = np.abs(np.expm1(np.maximum(y[:, 2], 0)) - np.expm1(t[:, 2]))
    return {"bearing_median_deg": float(np.median(db)), "bearing_p90_deg": float(np.percentile(db, 90)),
            "distance_median_m": float(np.median(dd)), "frames": int(len(t))}


def save(model: SoundLocalizer, path, meta: dict) -> None:
    from agents.models import write_checkpoint

    write_checkpoint(model, "sound-localizer", path, meta, half=True)


def load(path) -> tuple[SoundLocalizer, dict]:
    from agents.models import read_checkpoint

    return read_checkpoint(path, "sound-localizer", lambda c: SoundLocalizer(LocalizerConfig(**c)),
                           "sound-localiser checkpoint")


def train(cfg: LocalizerTrainConfig, out, progress=None) -> dict:
    """Collect, fit (smooth L1 on the three outputs), validate each epoch; writes ``out/localizer.pt`` (the epoch
    with the lowest validation median bearing error) and ``out/log.csv``."""
    from agents.imitation import append_row
    from sonicverse_core.errors import ConfigError

    out = Path(out)
    if (out / "localizer.pt").exists():
        raise ConfigError(f"{out / 'localizer.pt'} exists: choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    t0 = time.perf_counter()
    data = collect(cfg.task, "train", cfg.frames, rng, cfg.turn_prob, cfg.episode_steps)
    val = collect(cfg.task, "val", cfg.val_frames, np.random.default_rng([cfg.seed, 1]), cfg.turn_prob,
                  cfg.episode_steps)
    collect_s = time.perf_counter() - t0
    model = SoundLocalizer(LocalizerConfig(spec_shape=data["s"].shape[1:], lags=data["c"].shape[1]))
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, cfg.epochs)
    S, C, Y = (torch.from_numpy(data[k]) for k in ("s", "c", "y"))
    rows, best = [], None
    for ep in range(cfg.epochs):
        model.train()
        order = torch.from_numpy(rng.permutation(len(Y)))
        losses = []
        for i in range(0, len(order), cfg.batch):
            j = order[i:i + cfg.batch]
            loss = nn.functional.smooth_l1_loss(model(S[j].float() * (SPEC_MAX / 255), C[j]), Y[j])
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(float(loss.detach()))
        sched.step()
        model.eval()
        e = errors(model, val)
        row = {"epoch": ep, "loss": round(float(np.mean(losses)), 5), **{k: round(v, 3) for k, v in e.items()},
               "wall_s": round(time.perf_counter() - t0, 1)}
        rows.append(row)
        append_row(out / "log.csv", row, first=ep == 0)
        if best is None or e["bearing_median_deg"] < best:
            best = e["bearing_median_deg"]
            save(model, out / "localizer.pt", {"config": asdict(cfg), "log": rows, "collect_s": round(collect_s, 1),
                                               "train_frames": int(len(Y)), "val_frames": int(len(val["y"]))})
        if progress is not None:
            progress(row)
    return {"out": str(out), "checkpoint": str(out / "localizer.pt"), "log": rows}
