"""Learned agents as players of the evaluation harness: a checkpoint's policy acting on the sensors it was trained
on (the harness builds the env with :meth:`AVNavAgent.env_kwargs`), with its GRU state carried through an episode and
the mean action taken (no sampling)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from agents.scripted import Agent

CHECKPOINTS = Path(__file__).resolve().parent / "checkpoints"


def default_checkpoint(arch: str, task: str) -> Path:
    return CHECKPOINTS / f"{arch}_{task}.pt"


class AVNavAgent(Agent):
    name = "av-nav"

    def __init__(self, rng: np.random.Generator | None = None, checkpoint=None, task: str = "AudioGoal"):
        super().__init__(rng)
        from agents.models import load

        self.checkpoint = Path(checkpoint) if checkpoint else default_checkpoint("av-nav", task)
        self.model, self.meta = load(self.checkpoint)
        self.size = self.model.cfg.depth_hw[0]

    def env_kwargs(self) -> dict:
        from agents.imitation import SENSORS

        return {"sensors": SENSORS, "width": self.size, "height": self.size}

    def reset(self, env, obs, info) -> None:
        super().reset(env, obs, info)
        self.h = self.model.initial_state(1)
        self.start = True

    def act(self, obs, info) -> np.ndarray:
        from agents.imitation import _policy_step

        a, self.h = _policy_step(self.model, obs, self.h, self.start)
        self.start = False
        return np.clip(a, -1, 1).astype(np.float32)
