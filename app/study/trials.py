"""One study trial, run in a condition: ``TrialRunner.run(slot, check) -> (metrics, quality, raw)``.

Headless (the simulated participant; no VR loop): an orientation-training trial is one trial of
:class:`~sonicverse_core.tasks.orientation.OrientationTraining` with the study's listener model (and the condition's
overrides), its stimulus rendered in the condition (HRTF or panner, reverb or not) and its staircase carried through
the block (replayed from the committed trials on resume); a robot-task trial (speaker following, voice retrieval)
is one episode of the task's env in the condition with the simulated person and the condition's (or block's)
agent, its trajectory saved under ``raw/``.

desktop / openvr (a person): each trial is a VR session of the task's frame task (one orientation trial, or one
robot episode with the user as the person) on that backend, saved under ``raw/`` (input recording, the user's
ears, trajectory); its quality figures are the session's missed frames, xruns and audio latency.

``check()`` is called between steps; it raises to skip or abort the running trial.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sonicverse_core.errors import StudyError

NOT_MEASURED = {"missed_frames": None, "xruns": None, "latency_ms": None}


def _plain(d: dict) -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, (np.bool_, bool)):
            out[k] = bool(v)
        elif isinstance(v, np.generic):
            out[k] = v.item()
        elif isinstance(v, np.ndarray):
            continue
        else:
            out[k] = v
    return out


class TrialRunner:
    def __init__(self, study, store, pid: str, session: int, backend: str = "headless", audio_device=None):
        self.study, self.store, self.pid, self.session = study, store, pid, session
        self.backend, self.audio_device = backend, audio_device
        self._envs: dict = {}
        self._orient: dict = {}
        self._scored: int | None = None  # scored orientation trials so far in the session (the listener's practice)
        self.raw_dir = store.session_dir(pid, session) / "raw"

    def close(self) -> None:
        for env in self._envs.values():
            env.close()
        self._envs.clear()

    def _block(self, name: str):
        return next(b for b in self.study.blocks if b.name == name)

    def run(self, slot, check) -> tuple[dict, dict, dict]:
        from sonicverse_core.tasks.registry import task_spec

        cond = self.study.condition(slot.condition)
        blk = self._block(slot.block_name)
        spec = task_spec(slot.task)
        check()
        if self.backend != "headless":
            return self._vr(slot, cond, blk, spec, check)
        if spec.kind == "trials":
            return self._orientation(slot, cond, blk)
        return self._episode(slot, cond, blk, spec, check)

    # --- headless, simulated participant ----------------------------------------------------------------------
    def _orientation(self, slot, cond, blk):
        from sonicverse_core.tasks.orientation import OrientationTraining, SimulatedListener

        ot = self._orient.get(slot.block)
        if ot is None or self._scored is None:  # read what was committed once (a resume goes on where it was)
            done = [t for t in self.store.trials(self.pid, self.session) if t["task"] == slot.task]
            self._scored = sum(1 for t in done if not t["practice"])
        if ot is None:  # the block's staircase, replayed from the committed trials
            ot = self._orient[slot.block] = OrientationTraining(
                mode=blk.mode, trials=blk.trials, practice=blk.practice, difficulty=blk.difficulty,
                staircase=blk.staircase, hrtf=cond.hrtf, reverb=cond.reverb)
            for t in done:
                if t["block"] == slot.block and not t["practice"] and "correct" in t["metrics"]:
                    ot.staircases[blk.mode].update(bool(t["metrics"]["correct"]))
        listener = SimulatedListener(**{**self.study.simulated, **cond.simulated})
        row = ot.run_trial(slot.trial, "practice" if slot.practice else slot.block, blk.mode, listener,
                           np.random.default_rng(slot.seed), self._scored)
        self._scored += not slot.practice
        row["block"] = slot.block
        return _plain(row), dict(NOT_MEASURED), {}

    def _episode(self, slot, cond, blk, spec, check):
        from agents import make_agent
        from sonicverse_core.storage import atomic_write
        from sonicverse_core.tasks import make_env
        from sonicverse_core.tasks.base import TaskConfig

        key = (spec.name, cond.hrtf, cond.reverb, cond.home, blk.time_limit_s)
        env = self._envs.get(key)
        if env is None:
            kw = {"scenes": (cond.home,)} if cond.home else {}
            if blk.time_limit_s:  # the block's limit, as in the VR app (steps of the env's default 0.1 s)
                kw["max_steps"] = max(1, math.ceil(blk.time_limit_s / TaskConfig.step_seconds - 1e-9))
            env = self._envs[key] = make_env(spec.name, split="test", hrtf=cond.hrtf, reverb=cond.reverb, **kw)
        agent = cond.agent or blk.agent or spec.agents[0]
        obs, info = env.reset(seed=slot.seed)
        ag = make_agent(agent, np.random.default_rng(slot.seed), spec.name)
        ag.reset(env, obs, info)
        person = getattr(env.task, "person", None)
        track = {"t": [0.0], "robot": [env.home.world.pose[:3].copy()],
                 "person": [person.pos.copy()] if person is not None else [],
                 "distance": [float(env.task.dist)] if hasattr(env.task, "dist") else []}
        done, steps = False, 0
        while not done:
            check()
            obs, r, term, trunc, info = env.step(ag.act(obs, info))
            done = term or trunc
            steps += 1
            track["t"].append(steps * env.cfg.step_seconds)
            track["robot"].append(env.home.world.pose[:3].copy())
            if person is not None:
                track["person"].append(person.pos.copy())
            if track["distance"]:
                track["distance"].append(float(env.task.dist))
        raw = self.raw_dir / f"trial-{slot.slot:04d}.npz"
        with atomic_write(raw) as fh:
            np.savez(fh, t=np.array(track["t"]), robot=np.array(track["robot"]),
                     person=np.array(track["person"]) if track["person"] else np.zeros((0, 2)),
                     distance=np.array(track["distance"]))
        metrics = {**_plain(info["metrics"]), "agent": agent, "episode_id": env.episode.episode_id,
                   "scene": env.episode.scene}
        return metrics, dict(NOT_MEASURED), {"trajectory": str(raw.relative_to(self.store.root))}

    # --- a person, in the VR app ------------------------------------------------------------------------------
    def _vr(self, slot, cond, blk, spec, check):
        from app.tasks.in_the_loop import OrientationTrials, make_frame_task
        from app.vr import open_backend
        from app.vr.session import SessionConfig, VRSession
        from sonicverse_core.tasks.episodes import homes

        agent = (cond.agent or blk.agent) if spec.kind == "embodied" else None
        t = make_frame_task(spec.cli, agent, slot.seed, trials=1, mode=blk.mode)
        audio_only = isinstance(t, OrientationTrials)
        be = open_backend(self.backend, None, None)
        scene = cond.home or homes("test")[slot.seed % len(homes("test"))]
        cfg = SessionConfig(scene=scene, views=not audio_only, robots=0 if audio_only else 1, audio="live",
                            audio_device=self.audio_device, seed=slot.seed % (2**31), hrtf=cond.hrtf,
                            reverb=cond.reverb)
        limit = blk.time_limit_s or (60.0 if audio_only else spec.max_steps * 0.1)
        out = self.raw_dir / f"trial-{slot.slot:04d}"
        with VRSession(cfg, be, task=t) as sess:
            sess.run(frames=int(limit * be.target_hz))
            summ = sess.summary()
            sess.save(out)
        task = summ["task"]
        if audio_only:  # the one trial's row; none when the person did not answer within the limit
            metrics = _plain(task["rows"][0]) if task.get("rows") else {"_status": "no_response"}
        else:
            metrics = _plain({k: v for k, v in task.items() if k not in ("name", "rows")})
        tele = summ.get("audio_telemetry", {})
        quality = {"missed_frames": summ.get("missed_frames"), "xruns": tele.get("xruns"),
                   "latency_ms": (tele.get("reported_latency_ms") or {}).get("output")}
        return metrics, quality, {"session": str(Path(out).relative_to(self.store.root))}


def quality_flags(quality: dict, limits: dict) -> list[str]:
    """The figures of a trial beyond the study's thresholds."""
    out = []
    for k, lim in limits.items():
        v = quality.get(k)
        if v is not None and v > lim:
            out.append(f"{k} {v} > {lim}")
    return out


def require_backend(backend: str, simulated: bool) -> None:
    if backend not in ("headless", "desktop", "openvr"):
        raise StudyError(f"backend must be headless, desktop or openvr, got '{backend}'")
    if simulated and backend != "headless":
        raise StudyError("a simulated participant runs headless (--backend headless); desktop and openvr are for "
                         "people")
