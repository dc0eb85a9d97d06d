"""Imitation of the shortest-path oracle with DAgger (Ross et al. 2011), the first stage of the learned agents'
recipe (behaviour cloning then PPO, as PIRLNav and SPOC do): far fewer frames than PPO from scratch.

Each iteration drives ``frames`` steps in train homes with a mix of the expert and the policy (the expert acts with
probability ``beta``, which decays to ``beta_min``; collection episodes end after ``rollout_steps``), labels every
visited state with the expert's action (the oracle replans whenever the robot strays from its path), adds them to a
bounded dataset of episode sequences, and fits the policy to the labels (cross-entropy over the discrete head's
primitives, or mean squared error of the continuous head's mean; truncated back-propagation through time over ``seq``
steps), with the auxiliary goal-prediction loss (``aux_weight``) on where the goal is from the robot. Then it scores
SR / SPL on validation homes with the policy alone and saves a checkpoint and a CSV log line. ``resume`` goes on
from ``out/model.pt`` (weights, optimizer, random states, counters); the dataset is not saved (hundreds of MB)
and refills from the next rollouts.

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

from agents.models import (DEPTH_MAX, SPEC_MAX, AVNav, AVNavConfig, acting_threads, load, load_train_state,
                           primitives_for, save)

SENSORS = ("depth", "spectrogram", "pose")


@dataclass
class ImitationConfig:
    task: str = "AudioGoal"
    frames: int = 20_000  # total environment frames
    iterations: int = 10
    size: int = 64  # depth image side
    seq: int = 48
    batch: int = 16
    epochs: int = 4
    lr: float = 5e-4
    dataset_frames: int = 60_000
    val_episodes: int = 12
    head: str = "discrete"  # or "continuous"
    aux_weight: float = 0.5  # the goal-prediction loss (0: no goal heads)
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

    def goal(self) -> np.ndarray:
        """Where the goal (the middle of its terminal positions) is from the robot: cos and sin of its bearing and
        log(1 + distance in m): the auxiliary heads' target."""
        priv = self.oracle.env.privileged()
        pose = priv["world"].pose
        d = np.mean(priv["goals"], axis=0) - pose[:2]
        b = math.atan2(d[1], d[0]) - math.radians(pose[2])
        return np.array([math.cos(b), math.sin(b), math.log1p(math.hypot(*d))], np.float32)

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
    """(depth uint8 or None without a depth sensor, spectrogram uint8, pose float32) of an observation (or of a
    vector env's stacked observations): how the datasets store them."""
    d = (np.clip(np.round(obs["depth"][..., 0] / DEPTH_MAX * 255), 0, 255).astype(np.uint8) if "depth" in obs
         else None)
    s = np.clip(np.round(obs["spectrogram"] / SPEC_MAX * 255), 0, 255).astype(np.uint8)
    return d, s, obs["pose"].astype(np.float32)


def _stack(observations) -> tuple:
    """The quantised observations of several envs as tensors (1, B, ...) (depth None without a depth sensor)."""
    q = [_quantise(o) for o in observations]

    def t(i):
        return None if q[0][i] is None else torch.from_numpy(np.stack([x[i] for x in q]))[None]

    return t(0), t(1), t(2)


def _inputs(d, s, p) -> tuple:
    """The model's inputs from quantised tensors (``d`` may be None)."""
    return (d[..., None].float() * (DEPTH_MAX / 255) if d is not None else None, s.float() * (SPEC_MAX / 255),
            p.float())


def append_row(path, row: dict, first: bool) -> None:
    """A line of a training log (CSV); ``first`` starts the file with a header."""
    with open(path, "w" if first else "a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(row))
        if first:
            w.writeheader()
        w.writerow(row)


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
        keys = list(self.eps[0]) if self.eps else []
        for k in range(0, len(order), batch):
            sel = [chunks[j] for j in order[k:k + batch]]
            T = seq
            out = {key: [] for key in keys + ["m"]}
            for i, s in sel:
                e = self.eps[i]
                n = min(T, len(e["a"]) - s)
                for key in keys:
                    x = e[key][s:s + n]
                    pad = np.zeros((T - n,) + x.shape[1:], x.dtype)
                    out[key].append(np.concatenate([x, pad]))
                out["m"].append(np.concatenate([np.ones(n, np.float32), np.zeros(T - n, np.float32)]))
            yield {k: torch.from_numpy(np.stack(v, 1)) for k, v in out.items()}  # (T, B, ...)


def _policy_step(model, obs, h, start: bool, rng: np.random.Generator | None = None):
    """(action, next hidden state): the mean / most likely action, or with ``rng`` (discrete head) one drawn from
    the policy's distribution; a stop (tasks that have one) only when it is the most likely action, since a stop drawn
    by chance would end the episode."""
    with torch.no_grad(), acting_threads():
        out, _, h = model(*_inputs(*_stack([obs])), h, torch.tensor([[start]]))
    if rng is not None and model.discrete:
        prob = torch.softmax(out[0, 0].double(), -1).numpy()
        stop = model.table[:, 2].numpy() > 0 if model.table.shape[1] == 3 else np.zeros(len(prob), bool)
        if stop[int(np.argmax(prob))]:  # the stop ends the episode: taken only when it is the most likely action
            return model.table[int(np.argmax(prob))].numpy(), h
        prob = np.where(stop, 0.0, prob)
        return model.table[int(rng.choice(len(prob), p=prob / prob.sum()))].numpy(), h
    return model.act(out)[0, 0].numpy(), h


def bc_loss(model, b: dict, aux_weight: float) -> tuple[torch.Tensor, dict]:
    """The imitation loss on a batch of chunks (``d`` depth uint8, ``s`` spectrogram uint8, ``p`` pose, ``a`` the
    expert's actions, ``g`` the goal targets (optional), ``m`` the mask of real steps): cross-entropy (discrete head)
    or squared error (continuous head), plus ``aux_weight`` x the goal heads' squared errors."""
    m = b["m"]
    starts = torch.zeros(m.shape)
    starts[0] = 1.0
    y, a_feat, _ = model.features(*_inputs(b.get("d"), b["s"], b["p"]), model.initial_state(m.shape[1]), starts)
    out = model.head(y)
    if model.discrete:
        per = torch.nn.functional.cross_entropy(out.reshape(-1, out.shape[-1]), model.label(b["a"]).reshape(-1),
                                                reduction="none").reshape(m.shape)
    else:
        per = ((out - b["a"]) ** 2).sum(-1)
    policy = (per * m).sum() / m.sum()
    parts = {"policy": float(policy.detach())}
    loss = policy
    if aux_weight > 0 and model.cfg.aux_goal and "g" in b:
        g = b["g"]
        goal = ((((model.goal_head(y) - g) ** 2).sum(-1)) * m).sum() / m.sum()
        audio = ((((model.goal_audio(a_feat) - g) ** 2).sum(-1)) * m).sum() / m.sum()
        parts.update(goal=float(goal.detach()), goal_audio=float(audio.detach()))
        loss = loss + aux_weight * (goal + audio)
    return loss, parts


def evaluate(model, task: str, episodes: int, split: str, size: int, seed: int = 0) -> dict:
    """SR and SPL of the policy alone over ``episodes`` of ``split`` homes, acting as the ``av-nav`` agent does
    (actions drawn from the discrete head with a Generator seeded per episode; the continuous head's mean)."""
    from sonicverse_core.tasks import make_env

    env = make_env(task, split=split, sensors=SENSORS, width=size, height=size)
    sr, spl = [], []
    try:
        for i in range(episodes):
            obs, info = env.reset(seed=int(np.random.SeedSequence([seed, 7, i]).generate_state(1)[0]))
            h, start, done = model.initial_state(1), True, False
            draw = np.random.default_rng([seed, 8, i])
            while not done:
                a, h = _policy_step(model, obs, h, start, draw)
                start = False
                obs, _, term, trunc, info = env.step(a.astype(np.float32))
                done = term or trunc
            m = info.get("metrics", {})
            sr.append(float(m.get("success", 0.0)))
            spl.append(float(m.get("spl", 0.0)))
    finally:
        env.close()
    return {"sr": float(np.mean(sr)), "spl": float(np.mean(spl))}


def train(cfg: ImitationConfig, out, progress=None, resume: bool = False) -> dict:
    """Run DAgger for ``cfg.frames`` frames; checkpoints ``out/model.pt`` (every iteration, with the training state),
    ``out/best.pt`` (the best validation SR + SPL so far) and a line per iteration in ``out/log.csv``. ``resume``
    goes on from ``out/model.pt`` with the configuration it was started with (``cfg`` then only sets ``frames`` and
    ``iterations``, which may grow)."""
    from sonicverse_core.errors import ConfigError
    from sonicverse_core.tasks import make_env

    if cfg.frames < 1 or cfg.iterations < 1:
        raise ConfigError("--frames and --iterations must be >= 1")
    if cfg.head not in ("discrete", "continuous"):
        raise ConfigError(f"head must be discrete or continuous, got {cfg.head!r}")
    out = Path(out)
    ck_path = out / "model.pt"
    state, rows, frames, best, start_it = {}, [], 0, None, 0
    if resume:
        if not ck_path.is_file():
            raise ConfigError(f"nothing to resume: {ck_path} does not exist")
        model, meta = load(ck_path)
        state = load_train_state(ck_path)
        if not state:
            raise ConfigError(f"{ck_path} has no training state to resume from")
        old = ImitationConfig(**meta["config"])
        cfg = ImitationConfig(**{**asdict(old), "frames": cfg.frames, "iterations": cfg.iterations})
        rows, frames, best, start_it = meta["log"], state["frames"], state["best"], state["iteration"] + 1
        if start_it >= cfg.iterations:
            raise ConfigError(f"{ck_path} has done {start_it} of {cfg.iterations} iterations: raise --iterations")
    elif ck_path.exists():  # nothing already written is lost
        raise ConfigError(f"{ck_path} exists: choose another --out, or --resume")
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    env = make_env(cfg.task, split="train", sensors=SENSORS, width=cfg.size, height=cfg.size)
    spec = env.observation_space["spectrogram"].shape
    adim = env.action_space.shape[0]
    if not resume:
        model = AVNav(AVNavConfig(depth_hw=(cfg.size, cfg.size), spec_shape=spec, action_dim=adim,
                                  primitives=primitives_for(adim) if cfg.head == "discrete" else (),
                                  aux_goal=cfg.aux_weight > 0))
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    if resume:
        opt.load_state_dict(state["optimizer"])
        rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
    data = Dataset(cfg.dataset_frames)
    expert = Expert()
    per_iter = math.ceil(cfg.frames / cfg.iterations)
    log_path = out / "log.csv"
    for i, r in enumerate(rows):  # resumed: the log as far as the checkpoint (a kill may have left a later line)
        append_row(log_path, r, first=i == 0)
    t0 = time.perf_counter() - (rows[-1]["wall_s"] if rows else 0.0)
    try:
        for it in range(start_it, cfg.iterations):
            beta = max(cfg.beta_min, cfg.beta0 * (1 - it / max(cfg.iterations / 2, 1)))
            t_roll = time.perf_counter()
            n = 0
            while n < per_iter:
                obs, info = env.reset(seed=int(rng.integers(2**31)))
                expert.reset(env, obs, info)
                h, start, done = model.initial_state(1), True, False
                ep = {"d": [], "s": [], "p": [], "a": [], "g": []}
                while not done:
                    a_exp = expert.label(obs, info)
                    a_pol, h = _policy_step(model, obs, h, start)
                    d, s, p = _quantise(obs)
                    ep["d"].append(d)
                    ep["s"].append(s)
                    ep["p"].append(p)
                    ep["a"].append(a_exp.astype(np.float32))
                    ep["g"].append(expert.goal())
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
            parts = []
            for _ in range(cfg.epochs):
                for b in data.batches(rng, cfg.seq, cfg.batch):
                    loss, part = bc_loss(model, b, cfg.aux_weight)
                    opt.zero_grad()
                    loss.backward()
                    torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
                    opt.step()
                    parts.append(part)
            model.eval()
            fit_s = time.perf_counter() - t_fit
            val = evaluate(model, cfg.task, cfg.val_episodes, "val", cfg.size, cfg.seed) if cfg.val_episodes else {}
            row = {"iteration": it, "frames": frames, "beta": round(beta, 3),
                   "loss": round(float(np.mean([q["policy"] for q in parts])), 5),
                   "goal_loss": round(float(np.mean([q.get("goal", np.nan) for q in parts])), 5),
                   "goal_audio_loss": round(float(np.mean([q.get("goal_audio", np.nan) for q in parts])), 5),
                   "dataset_frames": data.frames, "rollout_fps": round(n / roll_s, 1),
                   "fit_s": round(fit_s, 2), "val_sr": val.get("sr"), "val_spl": val.get("spl"),
                   "wall_s": round(time.perf_counter() - t0, 1)}
            rows.append(row)
            append_row(log_path, row, first=it == 0)
            meta = {"recipe": "dagger", "config": asdict(cfg), "log": rows, "iteration": it}
            score = (val.get("sr") or 0.0) + (val.get("spl") or 0.0)
            if best is None or score > best:  # the best on validation homes (what is shipped)
                best = score
                save(model, out / "best.pt", meta)
            save(model, ck_path, meta, train_state={  # the latest (to go on from)
                "optimizer": opt.state_dict(), "rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state(),
                "frames": frames, "best": best, "iteration": it})
            if progress is not None:
                progress(row)
    finally:
        env.close()
    return {"out": str(out), "checkpoint": str(ck_path), "best": str(out / "best.pt"), "log": rows}
