"""Imitation of the shortest-path oracle with DAgger (Ross et al. 2011), the first stage of the learned agents'
recipe (behaviour cloning then PPO, as PIRLNav and SPOC do): far fewer frames than PPO from scratch.

Each iteration drives ``frames`` steps in train homes with a mix of the expert and the policy (the expert acts with
probability ``beta``, which decays to ``beta_min``; collection episodes end after ``rollout_steps``), labels every visited state with the expert's action (the oracle replans
whenever the robot strays from its path), adds them to a bounded dataset of episode sequences, and fits the policy's
mean action to the labels (mean squared error, truncated back-propagation through time over ``seq`` steps). Then it
scores SR / SPL on validation homes with the policy alone and saves a checkpoint and a CSV log line.

Observations are stored quantised to uint8 (depth over 0-10 m, spectrogram over 0-20): 10 KB a frame at 64 x 64.
"""
from __future__ import annotations

import csv
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from agents.models import DEPTH_MAX, SPEC_MAX, AVNav, AVNavConfig, save

SENSORS = ("depth", "spectrogram", "pose")


@dataclass
class ImitationConfig:
    task: str = "AudioGoal"
    frames: int = 20_000  # total environment frames
    iterations: int = 10
    size: int = 64  # depth image side
    seq: int = 32
    batch: int = 16
    epochs: int = 2
    lr: float = 5e-4
    dataset_frames: int = 60_000
    val_episodes: int = 8
    seed: int = 0
    beta0: float = 1.0  # the expert's share in the first iteration, decaying to beta_min by the middle of the run
    beta_min: float = 0.3  # (0 is DAgger's limit; here the learner's own stuck states then swamped the data)
    rollout_steps: int = 200  # a collection episode ends here (a stuck learner's 500 steps teach little)


class Expert:
    """The oracle's action at whatever state the robot is in: its path is replanned when the robot is more than
    ``stray`` m from it or bumps."""

    def __init__(self, stray: float = 0.35):
        from agents.scripted import OracleAgent

        self.oracle = OracleAgent(np.random.default_rng(0))
        self.stray = stray

    def reset(self, env, obs, info) -> None:
        self.oracle.reset(env, obs, info)

    def label(self, obs, info) -> np.ndarray:
        o = self.oracle
        p = o.env.privileged()["world"].pose[:2]
        seg = o.path[max(o.k - 1, 0):o.k + 1]
        if len(seg) >= 2:
            a, b = seg[0], seg[1]
            t = np.clip(np.dot(p - a, b - a) / max(np.dot(b - a, b - a), 1e-12), 0, 1)
            if np.linalg.norm(a + t * (b - a) - p) > self.stray:
                o._plan()
        return o.act(obs, info)


def _quantise(obs) -> tuple:
    d = np.clip(np.round(obs["depth"][..., 0] / DEPTH_MAX * 255), 0, 255).astype(np.uint8)
    s = np.clip(np.round(obs["spectrogram"] / SPEC_MAX * 255), 0, 255).astype(np.uint8)
    return d, s, obs["pose"].astype(np.float32)


class Dataset:
    """Episode sequences of (depth, spectrogram, pose, expert action), oldest dropped past ``cap`` frames."""

    def __init__(self, cap: int):
        self.cap, self.eps = cap, []

    def add(self, ep: dict) -> None:
        self.eps.append({k: np.stack(v) for k, v in ep.items()})
        while sum(len(e["a"]) for e in self.eps) > self.cap and len(self.eps) > 1:
            self.eps.pop(0)

    @property
    def frames(self) -> int:
        return sum(len(e["a"]) for e in self.eps)

    def batches(self, rng, seq: int, batch: int):
        """Shuffled chunks of ``seq`` steps (each starting its GRU from zero: the chunk's first step is a start)."""
        chunks = [(i, s) for i, e in enumerate(self.eps) for s in range(0, len(e["a"]), seq)]
        order = rng.permutation(len(chunks))
        for k in range(0, len(order), batch):
            sel = [chunks[j] for j in order[k:k + batch]]
            T = seq
            out = {"d": [], "s": [], "p": [], "a": [], "m": []}
            for i, s in sel:
                e = self.eps[i]
                n = min(T, len(e["a"]) - s)
                for key in ("d", "s", "p", "a"):
                    x = e[key][s:s + n]
                    pad = np.zeros((T - n,) + x.shape[1:], x.dtype)
                    out[key].append(np.concatenate([x, pad]))
                out["m"].append(np.concatenate([np.ones(n, np.float32), np.zeros(T - n, np.float32)]))
            yield {k: torch.from_numpy(np.stack(v, 1)) for k, v in out.items()}  # (T, B, ...)


def _policy_step(model, obs, h, start: bool):
    d, s, p = _quantise(obs)
    with torch.no_grad():
        mean, _, h = model(torch.from_numpy(d[None, None, ..., None]).float() * (DEPTH_MAX / 255),
                           torch.from_numpy(s[None, None]).float() * (SPEC_MAX / 255),
                           torch.from_numpy(p[None, None]), h, torch.tensor([[start]]))
    return mean[0, 0].numpy(), h


def evaluate(model, task: str, episodes: int, split: str, size: int, seed: int = 0) -> dict:
    """SR and SPL of the policy alone (mean action) over ``episodes`` of ``split`` homes."""
    from sonicverse_core.tasks import make_env

    env = make_env(task, split=split, sensors=SENSORS, width=size, height=size)
    sr, spl = [], []
    try:
        for i in range(episodes):
            obs, info = env.reset(seed=int(np.random.SeedSequence([seed, 7, i]).generate_state(1)[0]))
            h, start, done = model.initial_state(1), True, False
            while not done:
                a, h = _policy_step(model, obs, h, start)
                start = False
                obs, _, term, trunc, info = env.step(a.astype(np.float32))
                done = term or trunc
            m = info.get("metrics", {})
            sr.append(float(m.get("success", 0.0)))
            spl.append(float(m.get("spl", 0.0)))
    finally:
        env.close()
    return {"sr": float(np.mean(sr)), "spl": float(np.mean(spl))}


def train(cfg: ImitationConfig, out, progress=None) -> dict:
    """Run DAgger for ``cfg.frames`` frames; checkpoints ``out/model.pt`` (every iteration), ``out/best.pt`` (the best
    validation SR + SPL so far) and a line per iteration in ``out/log.csv``."""
    from sonicverse_core.errors import ConfigError
    from sonicverse_core.tasks import make_env

    if cfg.frames < 1 or cfg.iterations < 1:
        raise ConfigError("--frames and --iterations must be >= 1")
    out = Path(out)
    if (out / "model.pt").exists():  # nothing already written is lost (training does not resume yet)
        raise ConfigError(f"{out / 'model.pt'} exists: choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    env = make_env(cfg.task, split="train", sensors=SENSORS, width=cfg.size, height=cfg.size)
    spec = env.observation_space["spectrogram"].shape
    model = AVNav(AVNavConfig(depth_hw=(cfg.size, cfg.size), spec_shape=spec, action_dim=env.action_space.shape[0]))
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    data = Dataset(cfg.dataset_frames)
    expert = Expert()
    per_iter = math.ceil(cfg.frames / cfg.iterations)
    log_path = out / "log.csv"
    rows, t0, frames, best = [], time.perf_counter(), 0, None
    try:
        for it in range(cfg.iterations):
            beta = max(cfg.beta_min, cfg.beta0 * (1 - it / max(cfg.iterations / 2, 1)))
            t_roll = time.perf_counter()
            n = 0
            while n < per_iter:
                obs, info = env.reset(seed=int(rng.integers(2**31)))
                expert.reset(env, obs, info)
                h, start, done = model.initial_state(1), True, False
                ep = {"d": [], "s": [], "p": [], "a": []}
                while not done:
                    a_exp = expert.label(obs, info)
                    a_pol, h = _policy_step(model, obs, h, start)
                    d, s, p = _quantise(obs)
                    ep["d"].append(d)
                    ep["s"].append(s)
                    ep["p"].append(p)
                    ep["a"].append(a_exp.astype(np.float32))
                    start = False
                    act = a_exp if rng.random() < beta else a_pol
                    obs, _, term, trunc, info = env.step(np.asarray(act, np.float32))
                    n += 1
                    done = term or trunc or len(ep["a"]) >= cfg.rollout_steps
                data.add(ep)
            roll_s = time.perf_counter() - t_roll
            frames += n
            t_fit = time.perf_counter()
            model.train()
            losses = []
            for _ in range(cfg.epochs):
                for b in data.batches(rng, cfg.seq, cfg.batch):
                    starts = torch.zeros(b["m"].shape)
                    starts[0] = 1.0
                    mean, _, _ = model(b["d"][..., None].float() * (DEPTH_MAX / 255),
                                       b["s"].float() * (SPEC_MAX / 255), b["p"], model.initial_state(b["m"].shape[1]),
                                       starts)
                    loss = (((mean - b["a"]) ** 2).sum(-1) * b["m"]).sum() / b["m"].sum()
                    opt.zero_grad()
                    loss.backward()
                    torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
                    opt.step()
                    losses.append(float(loss.detach()))
            model.eval()
            fit_s = time.perf_counter() - t_fit
            val = evaluate(model, cfg.task, cfg.val_episodes, "val", cfg.size, cfg.seed) if cfg.val_episodes else {}
            row = {"iteration": it, "frames": frames, "beta": round(beta, 3), "loss": round(float(np.mean(losses)), 5),
                   "dataset_frames": data.frames, "rollout_fps": round(n / roll_s, 1),
                   "fit_s": round(fit_s, 2), "val_sr": val.get("sr"), "val_spl": val.get("spl"),
                   "wall_s": round(time.perf_counter() - t0, 1)}
            rows.append(row)
            new = not log_path.exists() or it == 0
            with open(log_path, "w" if it == 0 else "a", newline="") as f:
                w = csv.DictWriter(f, fieldnames=list(row))
                if new:
                    w.writeheader()
                w.writerow(row)
            meta = {"recipe": "dagger", "config": asdict(cfg), "log": rows, "iteration": it}
            save(model, out / "model.pt", meta)  # the latest (to go on from)
            score = (val.get("sr") or 0.0) + (val.get("spl") or 0.0)
            if best is None or score > best:  # the best on validation homes (what is shipped)
                best = score
                save(model, out / "best.pt", meta)
            if progress is not None:
                progress(row)
    finally:
        env.close()
    return {"out": str(out), "checkpoint": str(out / "model.pt"), "best": str(out / "best.pt"), "log": rows}
