"""DAgger's collection and validation in spawned processes (``sonicverse train --jobs J``): each job has its own
envs (and GL context) and receives the policy as it stands at each call; the fit stays in the training process.
"""
from __future__ import annotations

import math
from dataclasses import asdict

import numpy as np
import torch

from agents.imitation import NAV_VAL, ROLLOUT_STEPS, VAL_KEYS, ImitationConfig, eval_episodes, labellers, run_episode
from agents.maps import collect_sensors, ego_for, sensors_for


class Jobs:
    """DAgger's collection and validation in ``n`` spawned processes, each with its own envs (and GL context) and
    a copy of the policy on the CPU, sent as it is at each call; the fit stays in the caller's process (and device).
    Episode j of job k in iteration i draws from seed (cfg.seed, 11, i, k, j), whichever process plays it."""

    def __init__(self, cfg: ImitationConfig, n: int):
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        from sonicverse_core.tasks import worker_threads

        self.n = n
        self.ex = ProcessPoolExecutor(n, mp_context=mp.get_context("spawn"), initializer=_job_init,
                                      initargs=(asdict(cfg), worker_threads(n)))

    @staticmethod
    def _blob(model) -> bytes:
        import copy
        import io

        buf = io.BytesIO()
        torch.save(copy.deepcopy(model).to("cpu").eval(), buf)
        return buf.getvalue()

    def collect(self, model, beta: float, it: int, frames: int):
        """Episodes of at least ``frames`` steps in all (each job ``ceil(frames / n)``), job by job."""
        blob, share = self._blob(model), math.ceil(frames / self.n)
        futs = [self.ex.submit(_job_collect, blob, beta, it, k, share) for k in range(self.n)]
        for f in futs:
            yield from f.result()

    def evaluate(self, model, task: str, episodes: int, split: str, size: int, seed: int) -> list[dict]:
        blob = self._blob(model)
        futs = [self.ex.submit(_job_eval, blob, task, split, size, seed, list(range(k, episodes, self.n)))
                for k in range(self.n)]
        got = {}
        for k, f in enumerate(futs):
            got.update(zip(range(k, episodes, self.n), f.result()))
        return [got[i] for i in range(episodes)]

    def close(self, now: bool = False) -> None:
        """Shut the processes down; ``now``: without waiting for the jobs still running (they are terminated)."""
        if now:  # (ProcessPoolExecutor.terminate_workers from Python 3.14)
            for proc in list((getattr(self.ex, "_processes", None) or {}).values()):
                proc.terminate()
        self.ex.shutdown(wait=True, cancel_futures=True)


_JOB: dict = {}  # a job process's configuration and envs (by split)


def _job_init(cfg: dict, threads: int) -> None:
    from sonicverse_core.tasks import exit_with_parent, limit_threads

    exit_with_parent()
    limit_threads(threads)
    torch.set_num_threads(threads)
    _JOB.update(cfg=ImitationConfig(**cfg), envs={})


def _job_env(split: str, sensors: tuple):
    from sonicverse_core.tasks import make_env

    cfg = _JOB["cfg"]
    key = (split, sensors)
    if key not in _JOB["envs"]:
        _JOB["envs"][key] = make_env(cfg.task, split=split, sensors=sensors, width=cfg.size, height=cfg.size,
                                     homes=cfg.homes or None if split == "train" else None)
    return _JOB["envs"][key]


def _job_model(blob: bytes):
    import io

    return torch.load(io.BytesIO(blob), map_location="cpu", weights_only=False)


def _job_collect(blob: bytes, beta: float, it: int, k: int, frames: int) -> list[dict]:
    cfg = _JOB["cfg"]
    model = _job_model(blob)
    env = _job_env("train", collect_sensors(cfg))
    expert, ego = labellers(cfg, model)
    cap = cfg.rollout_steps or ROLLOUT_STEPS.get(cfg.task, 200)
    eps, n, j = [], 0, 0
    while n < frames:
        rng = np.random.default_rng([cfg.seed, 11, it, k, j])
        ep = run_episode(model, env, expert, ego, cfg, rng, int(rng.integers(2**31)), beta, cap)
        eps.append(ep)
        n += len(ep["a"])
        j += 1
    return eps


def _job_eval(blob: bytes, task: str, split: str, size: int, seed: int, indices: list) -> list[dict]:
    model = _job_model(blob)
    env = _job_env(split, sensors_for(model))
    return eval_episodes(model, env, ego_for(model), VAL_KEYS.get(task, NAV_VAL), indices, seed)
