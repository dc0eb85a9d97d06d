"""`sonicverse task run`: any task of the registry with one of its agents, headless.

Embodied tasks (a robot in a Gymnasium env): N episodes; episode i of a run with seed S is reset with seed
``SeedSequence([S, i])``, the agent gets ``default_rng`` of the same seed. Trial tasks (orientation training): a
session of trials with the simulated participant. Prints one JSON object with the task's metric keys (each
``{"mean", "ci95", "n"}``: Wilson intervals for rates, Student t otherwise), writes a per-episode or per-trial CSV
under ``--out`` (and a learning curve for orientation training) and, with ``maps``, a top-down picture of each
episode with the robot's (and the person's) trajectory.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from app.tasks.evaluate import episode_seed
from sonicverse_core.errors import ConfigError
from sonicverse_core.tasks.registry import TaskSpec, task_spec


def _write_csv(path: Path, rows: list[dict]) -> None:
    from sonicverse_core.storage import write_text_atomic

    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    w.writerows(rows)
    write_text_atomic(path, buf.getvalue())


def run_task(task: str, agent: str | None = None, episodes: int = 10, split: str = "test", seed: int = 0,
             out: str | Path | None = None, maps: str | Path | None = None, env_kwargs: dict | None = None,
             trials: int | None = None, participant: dict | None = None, task_kwargs: dict | None = None,
             progress: bool = False, checkpoint=None, first: int = 0, jobs: int = 1, resume: bool = False,
             overwrite: bool = False) -> dict:
    """``checkpoint``: a learned agent's weights (default: the one shipped for the task). Robot tasks play episodes
    ``first`` .. ``first + episodes - 1`` of the run with ``seed`` (episode i depends on the seed and i alone), in
    ``jobs`` processes (the rows one process gives), into a CSV under ``out`` rewritten after every episode, which
    ``resume`` completes and, without ``overwrite``, a run that would lose its rows does not replace (as ``sonicverse
    eval`` does: :func:`app.tasks.evaluate.run_episodes`)."""
    spec = task_spec(task)
    agent = agent or spec.agents[0]
    if first < 0:
        raise ConfigError(f"--first must be >= 0, got {first}")
    if overwrite and not out:
        raise ConfigError("--overwrite replaces the CSV in --out, and there is none: give --out")
    if spec.kind == "trials":
        for flag, v in (("--first", first), ("--jobs", jobs > 1), ("--resume", resume)):
            if v:
                raise ConfigError(f"{flag} is for robot tasks' episodes; {spec.cli} runs trials")
        if agent not in spec.agents:
            raise ConfigError(f"unknown agent '{agent}' for {spec.cli}; use one of {', '.join(spec.agents)}")
        if checkpoint is not None:
            raise ConfigError(f"{spec.cli} has no learned agents: no --checkpoint")
        return _run_trials(spec, agent, trials or episodes, seed, out, participant or {}, task_kwargs or {},
                           progress, overwrite)
    return _run_embodied(spec, agent, episodes, split, seed, out, maps, env_kwargs or {}, progress, checkpoint, first,
                         jobs, resume, overwrite)


def _run_embodied(spec: TaskSpec, agent: str, episodes: int, split: str, seed: int, out, maps, kw: dict,
                  progress: bool, checkpoint=None, first: int = 0, jobs: int = 1, resume: bool = False,
                  overwrite: bool = False) -> dict:
    from agents import make_agent
    from app.tasks.evaluate import check_jobs, csv_name, run_episodes, run_identity
    from sonicverse_core.tasks.metrics import mean_ci95, rate_ci95

    if episodes < 1:
        raise ConfigError(f"--episodes must be >= 1, got {episodes}")
    check_jobs(jobs)
    if resume and not out:
        raise ConfigError("--resume continues the run whose CSV is in --out: give it")
    if resume and overwrite:
        raise ConfigError("--resume keeps the CSV's episodes and --overwrite drops them: give one")
    probe = make_agent(agent, np.random.default_rng(seed), spec.name, checkpoint=checkpoint)  # fails early
    meta = run_identity(spec.name, agent, split, None, seed, kw, getattr(probe, "checkpoint", None) or checkpoint)
    kw = {**kw, **getattr(probe, "env_kwargs", lambda: {})()}  # the sensors a learned agent was trained on
    csv_path = Path(out) / csv_name(spec.cli, agent, split, seed, first) if out else None
    rows = run_episodes(list(range(first, first + episodes)), _play_embodied,
                        (spec.name, agent, split, seed, kw, maps, checkpoint), jobs=jobs, path=csv_path, meta=meta,
                        resume=resume, overwrite=overwrite, fields=None, progress=(lambda i, row: None) if progress else None,
                        desc=f"{spec.cli} {agent}")
    res = {"task": spec.cli, "agent": agent, "episodes": len(rows), "first": first, "split": split, "seed": seed}
    for key in spec.metrics:
        col = "success" if key == "sr" else key
        res[key] = (rate_ci95 if key in spec.rates else mean_ci95)(r[col] for r in rows)
    if csv_path:
        res["csv"] = str(csv_path)
    return res


def _play_embodied(indices, task: str, agent: str, split: str, seed: int, kw: dict, maps, checkpoint, report,
                   bar: bool = False) -> None:
    """Play the episodes ``indices`` in one env, calling ``report(i, row)`` (the CSV row) after each."""
    from agents import make_agent
    from sonicverse_core.progress import progress
    from sonicverse_core.tasks import make_env

    spec = task_spec(task)
    env = make_env(spec.name, split=split, **kw)
    try:
        for i in progress(indices, desc=f"{spec.cli} {agent}", enabled=bar):
            s = episode_seed(seed, i)
            obs, info = env.reset(seed=s)
            ag = make_agent(agent, np.random.default_rng(s), spec.name, checkpoint=checkpoint)
            ag.reset(env, obs, info)
            robot = [env.home.world.pose[:2].copy()]
            person = [env.task.person.pos.copy()] if hasattr(env.task, "person") else None
            total, done = 0.0, False
            while not done:
                obs, r, term, trunc, info = env.step(ag.act(obs, info))
                total += r
                done = term or trunc
                robot.append(env.home.world.pose[:2].copy())
                if person is not None:
                    person.append(env.task.person.pos.copy())
            m = info["metrics"]
            if maps:
                _write_map(env, np.array(robot), None if person is None else np.array(person),
                           Path(maps) / f"episode_{i:04d}.png", spec, m)
            report(i, {"episode": i, "episode_id": env.episode.episode_id, "scene": env.episode.scene,
                       "reward": round(total, 4), **m})
    finally:
        env.close()


def _write_map(env, robot, person, out: Path, spec: TaskSpec, m: dict) -> None:
    from sonicverse_core.scene.topdown import draw_map

    out.parent.mkdir(parents=True, exist_ok=True)
    markers = {"robot start": (robot[0, 0], robot[0, 1], "g^"), "robot end": (robot[-1, 0], robot[-1, 1], "ks")}
    paths = [robot]
    if person is not None:
        paths.append(person)
        markers["person end"] = (person[-1, 0], person[-1, 1], "r*")
    elif hasattr(env.task, "goals"):
        g = env.task.goals[0]
        markers["goal"] = (g[0], g[1], "r*")
    title = f"{spec.cli} {env.episode.episode_id}: " + ", ".join(
        f"{k} {m[k]:.2f}" for k in spec.metrics if k in m and isinstance(m[k], (int, float)))
    draw_map(env.home.scene, out, grid=env.home.world.grid, paths=paths, markers=markers, title=title[:100],
             path_labels=["robot", "person"][:len(paths)])


def _settings_diff(old: dict, new: dict) -> str:
    """``'trials 6 (now 8), noise_deg 10.0 (now 30.0)'``: the settings (one level of nested dicts flattened) that
    differ between two runs' ``.csv.json``."""
    def flat(m: dict) -> dict:
        return {f"{k}.{j}" if isinstance(v, dict) else k: w for k, v in m.items()
                for j, w in (v.items() if isinstance(v, dict) else [(None, v)])}

    was, now = flat(old), flat(new)
    return ", ".join(f"{k.split('.')[-1]} {was.get(k)} (now {now.get(k)})" for k in sorted(set(was) | set(now))
                     if was.get(k) != now.get(k))


def _run_trials(spec: TaskSpec, agent: str, trials: int, seed: int, out, participant: dict, task_kwargs: dict,
                progress: bool, overwrite: bool = False) -> dict:
    """A simulated listener's session; its CSV under ``out`` (with ``.csv.json``: the settings it ran with) replaces
    an earlier one only when the earlier ran with the same settings (the same trials again: the run is
    deterministic), or with ``overwrite``."""
    import json

    from app.tasks.evaluate import identity_path, read_identity
    from sonicverse_core.storage import write_text_atomic
    from sonicverse_core.tasks.orientation import SimulatedListener, learning_curve

    cls = spec.load()
    kw = dict(task_kwargs)
    kw.setdefault("trials", trials)
    runner = cls(**kw)
    listener = SimulatedListener(**participant)
    p = Path(out) / f"{spec.cli}_{agent}_s{seed}.csv" if out else None
    if p is not None:
        meta = json.loads(json.dumps({"task": spec.cli, "agent": agent, "seed": seed, "task_kwargs": kw,
                                      "participant": participant}, default=str))
        if p.exists() and not overwrite:
            old = read_identity(p)
            if old != meta:
                why = (f"{identity_path(p).name} (what it ran) is missing or unreadable" if old is None else
                       f"it ran with other settings: {_settings_diff(old, meta)}")
                raise ConfigError(f"{p} is kept from an earlier run ({why}): give another --out, or --overwrite to "
                                  "replace it")
        write_text_atomic(identity_path(p), json.dumps(meta, indent=1) + "\n")
    done: list[dict] = []

    def keep(i, row):  # on disk every 10 trials (atomically): an interrupted session loses at most 9
        done.append(row)
        if p is not None and i % 10 == 9:
            _write_csv(p, done)

    rows = runner.run(listener, np.random.default_rng(seed), on_trial=keep)
    res = {"task": spec.cli, "agent": agent, "seed": seed, **runner.summary(rows)}
    if out:
        d = Path(out)
        _write_csv(p, rows)
        png = d / f"{spec.cli}_{agent}_s{seed}_learning_curve.png"
        learning_curve(rows, png)
        res["csv"], res["learning_curve"] = str(p), str(png)
    return res


def run_in_vr(task: str, agent: str | None = None, episodes: int = 1, split: str = "test", seed: int = 0,
              backend: str = "desktop", out: str | Path | None = None, trials: int = 10, mode: str = "turn",
              rate: float | None = None, size=None, max_seconds: float | None = None, hrtf: bool = True,
              reverb: bool = True, scene: str | None = None, overwrite: bool = False) -> dict:
    """``task run --backend desktop|openvr``: the task in the VR app with the user as the person, one session per
    episode (orientation training: one session of ``trials`` trials), each in a home of ``split`` and ending when
    the task does (or the user closes the window / quits, or after ``max_seconds``: the task's own limit). Returns
    the task's metric keys with 95% CIs over the episodes (trials), as :func:`run_task` does, and writes a CSV
    (rewritten after each session). A person's sessions cannot be played again: a CSV already there is refused
    before anything starts, unless ``overwrite``."""
    from app.tasks.in_the_loop import OrientationTrials, make_frame_task
    from app.vr import open_backend
    from app.vr.session import SessionConfig, VRSession
    from sonicverse_core.tasks.episodes import homes
    from sonicverse_core.tasks.metrics import mean_ci95, rate_ci95

    spec = task_spec(task)
    if spec.frame_task is None:
        raise ConfigError(f"task '{spec.cli}' has no VR version")
    if overwrite and not out:
        raise ConfigError("--overwrite replaces the CSV in --out, and there is none: give --out")
    scenes = [scene] if scene else homes(split)
    rows: list[dict] = []
    csv_path = Path(out) / f"{spec.cli}_{agent or spec.agents[0]}_{backend}_s{seed}.csv" if out else None
    if csv_path is not None and csv_path.exists() and not overwrite:
        raise ConfigError(f"{csv_path} holds an earlier session's rows (a person's sessions cannot be played "
                          "again): give another --out, or --overwrite to replace it")
    n = 1 if spec.kind == "trials" else episodes
    for i in range(n):
        s_i = episode_seed(seed, i)
        t = make_frame_task(spec.cli, agent, s_i, trials=trials, mode=mode)
        audio_only = isinstance(t, OrientationTrials)
        be = open_backend(backend, size, rate or (30.0 if backend == "headless" else None))
        limit = max_seconds or (spec.max_steps * 0.1 if not audio_only else 60.0 * trials)
        cfg = SessionConfig(scene=scenes[i % len(scenes)], views=not audio_only, robots=0 if audio_only else 1,
                            audio="offline" if backend == "headless" else "live", seed=s_i, hrtf=hrtf, reverb=reverb)
        with VRSession(cfg, be, task=t) as sess:
            sess.run(frames=int(limit * be.target_hz))
            summ = sess.summary()["task"]
        if audio_only:
            rows += summ["rows"]
        else:
            rows.append({"episode": i, "scene": cfg.scene, **{k: v for k, v in summ.items() if k != "name"}})
        if csv_path:
            _write_csv(csv_path, rows)
    res = {"task": spec.cli, "agent": agent or spec.agents[0], "backend": backend, "episodes": n, "seed": seed}
    for key in spec.metrics:
        col = {"front_back_confusion_rate": "front_back_confusion"}.get(key, key)
        vals = [r.get(col) for r in rows]
        vals = [float("nan") if v is None else float(v) for v in vals]
        if key in spec.rates:
            ok = [v for v in vals if v == v]
            res[key] = rate_ci95(ok)
        else:
            res[key] = mean_ci95(vals)
    if audio_only:
        res["trials"] = len(rows)
    if csv_path:
        res["csv"] = str(csv_path)
    return res
