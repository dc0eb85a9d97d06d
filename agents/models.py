"""Learned policies in torch (CPU by default, CUDA when present).

:class:`AVNav`: the audio-visual navigation policy of SoundSpaces (Chen et al. 2020): a CNN over the depth image, a
CNN over the binaural spectrogram, the odometry pose, a GRU over time, and an actor-critic head. The action is the
TurtleBot's two wheel velocities in [-1, 1] (plus a stop output on tasks that have one): a Gaussian whose mean is
squashed by tanh, with a learned log standard deviation (used by PPO; imitation and evaluation use the mean).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

DEPTH_MAX = 10.0
SPEC_MAX = 20.0


@dataclass(frozen=True)
class AVNavConfig:
    depth_hw: tuple = (64, 64)
    spec_shape: tuple = (2, 64, 49)
    pose_dim: int = 4
    action_dim: int = 2
    hidden: int = 256


def _cnn(in_ch: int, hw: tuple, out: int, k=(8, 4, 3), s=(4, 2, 1)) -> nn.Sequential:
    layers, ch, h, w = [], in_ch, hw[0], hw[1]
    for kk, ss, oc in zip(k, s, (32, 64, 64)):
        layers += [nn.Conv2d(ch, oc, kk, ss), nn.ReLU()]
        ch, h, w = oc, (h - kk) // ss + 1, (w - kk) // ss + 1
    if h < 1 or w < 1:
        raise ValueError(f"input {hw} too small for the encoder")
    return nn.Sequential(*layers, nn.Flatten(), nn.Linear(ch * h * w, out), nn.ReLU())


class AVNav(nn.Module):
    """``forward(depth (T, B, H, W, 1), spec (T, B, 2, F, W), pose (T, B, 4), hidden (1, B, H), starts (T, B))`` ->
    (action mean (T, B, A) in [-1, 1], value (T, B), hidden). ``starts`` marks each episode's first step: the GRU's
    state is zeroed there."""

    def __init__(self, cfg: AVNavConfig = AVNavConfig()):
        super().__init__()
        self.cfg = cfg
        h = cfg.hidden
        self.depth = _cnn(1, cfg.depth_hw, h)
        self.audio = _cnn(cfg.spec_shape[0], cfg.spec_shape[1:], h, k=(5, 3, 3), s=(2, 2, 1))
        self.gru = nn.GRU(2 * h + cfg.pose_dim, h)
        self.actor = nn.Linear(h, cfg.action_dim)
        self.critic = nn.Linear(h, 1)
        self.log_std = nn.Parameter(torch.full((cfg.action_dim,), -0.5))

    def initial_state(self, batch: int) -> torch.Tensor:
        return torch.zeros(1, batch, self.cfg.hidden)

    def encode(self, depth, spec, pose) -> torch.Tensor:
        T, B = depth.shape[:2]
        d = (depth.reshape(T * B, *depth.shape[2:]).permute(0, 3, 1, 2).float() / DEPTH_MAX).clamp(0, 1)
        a = (spec.reshape(T * B, *spec.shape[2:]).float() / SPEC_MAX).clamp(0, 1)
        x = torch.cat([self.depth(d), self.audio(a), pose.reshape(T * B, -1).float()], 1)
        return x.reshape(T, B, -1)

    def forward(self, depth, spec, pose, hidden, starts):
        x = self.encode(depth, spec, pose)
        outs = []
        for t in range(x.shape[0]):  # reset the state at episode starts (sequences may span episodes)
            hidden = hidden * (1.0 - starts[t].float()).view(1, -1, 1)
            o, hidden = self.gru(x[t:t + 1], hidden)
            outs.append(o)
        y = torch.cat(outs, 0)
        return torch.tanh(self.actor(y)), self.critic(y).squeeze(-1), hidden


def save(model: AVNav, path, meta: dict, half: bool = False) -> None:
    """Write a checkpoint atomically; ``half`` stores the weights as float16 (half the size, for shipping; they load
    back as float32)."""
    from sonicverse_core.storage import atomic_write

    state = {k: v.half() if half and v.is_floating_point() else v for k, v in model.state_dict().items()}
    with atomic_write(path) as f:
        torch.save({"arch": "av-nav", "config": asdict(model.cfg), "state": state, "meta": meta}, f)


def load(path) -> tuple[AVNav, dict]:
    from pathlib import Path

    from sonicverse_core.errors import ConfigError

    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"checkpoint not found: {p}")
    try:
        ck = torch.load(p, map_location="cpu", weights_only=False)
        cfg = AVNavConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in ck["config"].items()})
        model = AVNav(cfg)
        model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in ck["state"].items()})
    except Exception as exc:  # a damaged or foreign file: one clear line
        raise ConfigError(f"{p} is not a Sonicverse AV-Nav checkpoint ({type(exc).__name__}: {exc})") from None
    model.eval()
    return model, ck.get("meta", {})
