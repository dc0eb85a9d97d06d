"""`sonicverse eval`: run an agent over N episodes of a task, print mean metrics with 95% confidence intervals,
write a per-episode CSV, and optionally a top-down trajectory map and a frames + audio folder per episode.

Episode i of a run with seed S is reset with seed ``SeedSequence([S, i])``: the same command gives the same
episodes, and the same agent (seeded the same way) the same trajectories.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from sonicverse_core.errors import ConfigError

from sonicverse_core.tasks.registry import navigation

TASK_NAMES = tuple(s.name for s in navigation())
CSV_FIELDS = ("episode", "episode_id", "scene", "category", "object", "sound", "sound_seconds", "geodesic",
              "success", "spl", "sna", "soft_spl", "distance_to_goal", "path_length", "steps", "n_star", "collisions",
              "reward")


def episode_seed(seed: int, i: int) -> int:
    return int(np.random.SeedSequence([seed, i]).generate_state(1)[0])


def make_env(task: str, **kwargs):
    from sonicverse_core.tasks import make_env as make

    return make(task, **kwargs)


def run_eval(task: str, agent: str, episodes: int, split: str = "test", sounds: str = "heard", seed: int = 0,
             csv_path: str | Path | None = None, maps: str | Path | None = None, video: str | Path | None = None,
             env_kwargs: dict | None = None, progress=None, checkpoint=None, first: int = 0, jobs: int = 1,
             resume: bool = False, overwrite: bool = False) -> dict:
    """Episodes ``first`` .. ``first + episodes - 1`` of the run with ``seed``. Episode i depends on the seed and i
    alone, so ``jobs`` > 1 plays them in that many processes (interleaved: job j plays every jobs-th, from the j-th)
    and gives the rows, the CSV and the metrics a single process gives (tested); the cores are shared out between
    the jobs' renderers and math libraries. ``progress(i, row)`` is called in this process as each episode ends.

    The CSV is rewritten (atomically) after every episode, beside a ``.json`` of what was evaluated: an interrupted
    or killed run keeps every finished episode, and ``resume`` plays only the episodes the CSV lacks (refused when
    the CSV belongs to another evaluation: task, agent, checkpoint, seed, split, sounds, env settings). Without
    ``resume`` an existing CSV is replaced only by a rerun of the same evaluation over the same episodes; one that
    would lose rows (an interrupted run's, another evaluation's, other episodes) is refused unless ``overwrite``."""
    from agents import make_agent

    if episodes < 1:
        raise ConfigError(f"--episodes must be >= 1, got {episodes}")
    if first < 0:
        raise ConfigError(f"--first must be >= 0, got {first}")
    check_jobs(jobs)
    if resume and not csv_path:
        raise ConfigError("--resume continues the evaluation whose CSV --csv names: give it")
    if resume and overwrite:
        raise ConfigError("--resume keeps the CSV's episodes and --overwrite drops them: give one")
    kw = dict(env_kwargs or {})
    probe = make_agent(agent, np.random.default_rng(seed), task, checkpoint=checkpoint)  # fails early, names its env
    meta = run_identity(task, agent, split, sounds, seed, kw, getattr(probe, "checkpoint", None) or checkpoint)
    kw.update(getattr(probe, "env_kwargs", lambda: {})())
    if video:
        kw.setdefault("render_mode", "rgb_array")
    indices = list(range(first, first + episodes))
    path = Path(csv_path) if csv_path else None
    rows = run_episodes(indices, _play, (task, agent, split, sounds, seed, kw, maps, video, checkpoint), jobs=jobs,
                        path=path, meta=meta, resume=resume, fields=CSV_FIELDS, progress=progress,
                        desc=f"{task} {agent}", overwrite=overwrite)
    return _summary(rows, task, agent, split, sounds, seed, first, path)


def csv_name(task: str, agent: str, split: str, seed: int, first: int = 0, sounds: str | None = None) -> str:
    """The default CSV's name of a run: a part that starts at episode ``first`` > 0 has its own (``_fromK``), so
    the parts of a long run written to one folder do not overwrite each other."""
    mid = f"_{sounds}" if sounds else ""
    return f"{task}_{agent.replace(':', '.')}_{split}{mid}_s{seed}{f'_from{first}' if first else ''}.csv"


def check_jobs(jobs: int) -> None:
    """``--jobs``: at least 1, at most the machine's cores (each job holds an env, a GL context and a model: more
    than the cores only costs memory)."""
    from sonicverse_core.tasks import cores as machine_cores

    if jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {jobs}")
    cores = machine_cores()
    if jobs > cores:
        raise ConfigError(f"--jobs {jobs} is more than this machine's {cores} cores: use at most {cores}")


def run_episodes(indices: list[int], play, args: tuple, *, jobs: int = 1, path: Path | None = None,
                 meta: dict | None = None, resume: bool = False, fields: tuple | None = None, progress=None,
                 desc: str = "", overwrite: bool = False) -> list[dict]:
    """The rows of episodes ``indices``, played by ``play(indices, *args, report=, bar=)`` (a module-level function:
    ``jobs`` > 1 runs it in that many spawned processes, interleaved) and kept in the CSV ``path`` (rewritten
    atomically after every episode, ``meta`` beside it; ``fields`` its columns, None: the rows' keys). ``resume``
    plays only the episodes the CSV lacks; without it, a CSV there that this run would not repeat in full is refused
    (:func:`_keep_earlier`) unless ``overwrite``. ``progress(i, row)`` is called here as each episode ends. An
    interruption raises :class:`errors.Interrupted`, saying what the CSV keeps."""
    from sonicverse_core import errors

    if resume:
        rows = _resumed(path, meta, indices, fields)
    else:
        rows = {}
        if path and not overwrite:
            _keep_earlier(path, meta, indices, fields)
    todo = [i for i in indices if i not in rows]
    written = []  # the identity goes beside the CSV with its first row

    def sink(i, row):
        rows[i] = row
        if path:
            _write_rows(path, rows, meta if not written else None, fields)
            written.append(i)
        if progress:
            progress(i, row)

    try:
        if jobs > 1 and len(todo) > 1:
            _play_in_jobs(todo, min(jobs, len(todo)), play, args, sink, desc, bar=progress is not None)
        elif todo:
            play(todo, *args, report=sink, bar=progress is not None)
    except BaseException as exc:
        stop = exc if isinstance(exc, KeyboardInterrupt) else errors.stop_behind(exc)  # SIGTERM's, maybe wrapped
        if stop is None:
            raise
        n = len(rows)
        kept = (f"{path} keeps its {n} finished episode{'s' if n > 1 else ''}: add --resume to play the rest"
                if path and rows else "no episode had finished")
        raise errors.Interrupted(f"{str(stop) or 'interrupted'}; {kept}") from None
    return [rows[i] for i in indices]


def run_identity(task, agent, split, sounds, seed, kw, checkpoint) -> dict:
    """What an evaluation's rows depend on, written beside its CSV: a resumed run must match it (a learned agent's
    weights by their hash: the shipped default included)."""
    import hashlib

    ck = None
    if checkpoint:
        ck = {"path": str(checkpoint), "sha256": hashlib.sha256(Path(checkpoint).read_bytes()).hexdigest()}
    return {"task": task, "agent": agent, "split": split, "sounds": sounds, "seed": int(seed),
            "env": {k: kw[k] for k in sorted(kw)}, "checkpoint": ck}


def identity_path(path: Path) -> Path:
    """Where a run's CSV keeps what wrote it (``NAME.csv.json``)."""
    return path.with_name(path.name + ".json")


def read_identity(path: Path) -> dict | None:
    """The identity the run that wrote the CSV ``path`` left beside it; None where that file is missing, unreadable
    or not a JSON object."""
    import json

    try:
        old = json.loads(identity_path(path).read_text())
    except (OSError, ValueError):
        return None
    return old if isinstance(old, dict) else None


def _write_rows(path: Path, rows: dict, meta: dict | None, fields: tuple | None = CSV_FIELDS) -> None:
    """The CSV, rows in episode order (atomically; ``fields`` its columns, None: the rows' keys in order of first
    appearance); with ``meta``, its identity beside it first."""
    import io
    import json

    from sonicverse_core.storage import write_text_atomic

    path.parent.mkdir(parents=True, exist_ok=True)
    if meta is not None:
        write_text_atomic(identity_path(path), json.dumps(meta, indent=1, default=str) + "\n")
    if fields is None:
        fields = list(dict.fromkeys(k for i in sorted(rows) for k in rows[i]))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields)
    w.writeheader()
    w.writerows(rows[i] for i in sorted(rows))
    write_text_atomic(path, buf.getvalue())


def _keep_earlier(path: Path, meta: dict, indices: list[int], fields: tuple | None = CSV_FIELDS) -> None:
    """Refuses to start a run that would replace the CSV at ``path`` and lose rows: those an interrupted run of the
    same evaluation left (--resume plays the rest), another evaluation's, other episodes', or a file that is not an
    evaluation's. A rerun of the same evaluation over the same episodes replaces it (it measures the same thing)."""
    if not path.exists():
        return
    again = "give another file (--csv, --out) or --overwrite to replace it"
    try:
        rows = _earlier_rows(path, meta, indices, fields)
    except _Foreign as exc:
        raise ConfigError(f"{path} is kept from an earlier run ({exc}): {again}") from None
    missing = len(set(indices) - set(rows))
    if missing:
        n = len(rows)
        raise ConfigError(f"{path} keeps {n} finished episode{'s' if n != 1 else ''} of this evaluation, of the "
                          f"{len(indices)} asked for: add --resume to play the other {missing}, or {again}")


def _resumed(path: Path, meta: dict, indices: list[int], fields: tuple | None = CSV_FIELDS) -> dict:
    """The rows an interrupted evaluation left in ``path``, by episode (none where there is no CSV yet); ``fields``:
    its columns (None: any that start with the episode's index)."""
    if not path.exists():
        return {}
    try:
        return _earlier_rows(path, meta, indices, fields)
    except _Foreign as exc:
        tail = "; use another --csv or drop --resume" if exc.args[0].startswith("it holds another") else ""
        raise ConfigError(f"cannot resume {path}: {exc}{tail}") from None


class _Foreign(Exception):
    """Why a CSV is not (part of) the evaluation asked for."""


def _earlier_rows(path: Path, meta: dict, indices: list[int], fields: tuple | None) -> dict:
    """The rows of the existing CSV ``path`` by episode, when it holds episodes of this evaluation (``meta``) among
    ``indices``; else :class:`_Foreign` says why not."""
    import json

    old = read_identity(path)
    if old is None:
        raise _Foreign(f"{identity_path(path).name} (what it evaluated) is missing or unreadable")
    if old != json.loads(json.dumps(meta, default=str)):
        diff = sorted(k for k in set(old) | set(meta) if old.get(k) != json.loads(json.dumps(meta.get(k),
                                                                                              default=str)))
        raise _Foreign(f"it holds another evaluation (its {', '.join(diff)} "
                       f"{'differs' if len(diff) == 1 else 'differ'})")
    rows = {}
    try:
        with path.open(newline="") as f:
            reader = csv.DictReader(f)
            head = tuple(reader.fieldnames or ())
            if (head != fields) if fields is not None else (not head or head[0] != "episode"):
                raise ValueError("its header is not the evaluation's columns")
            for r in reader:
                if None in r or None in r.values():
                    raise ValueError(f"line {reader.line_num} has {'more' if None in r else 'fewer'} cells than "
                                     "the header")
                row = {k: _number(v) for k, v in r.items()}
                if not isinstance(row["episode"], int):
                    raise ValueError(f"line {reader.line_num}: episode '{row['episode']}' is not a number")
                rows[row["episode"]] = row
    except (OSError, ValueError, csv.Error) as exc:
        raise _Foreign(f"not an evaluation CSV ({exc})") from None
    outside = sorted(set(rows) - set(indices))
    if outside:
        raise _Foreign(f"it holds episode {outside[0]}, outside the episodes asked for "
                       f"({indices[0]} .. {indices[-1]}: --first, --episodes)")
    return rows


def _number(v: str):
    """A CSV cell back to what was written: int, float (inf and nan too) or text."""
    for f in (int, float):
        try:
            return f(v)
        except ValueError:
            pass
    return v


def _play(indices, task, agent, split, sounds, seed, kw, maps, video, checkpoint, report, bar: bool = False) -> None:
    """Play the episodes ``indices`` in one env, calling ``report(i, row)`` (the CSV row) after each."""
    from agents import make_agent
    from sonicverse_core.errors import check_stopped
    from sonicverse_core.progress import progress

    env = make_env(task, split=split, sounds=sounds, **kw)
    if video:
        env.unwrapped.hear = True  # the video's sound track is what the robot heard, whatever the agent reads
    try:
        for i in progress(indices, desc=f"{task} {agent}", enabled=bar):
            s = episode_seed(seed, i)
            obs, info = env.reset(seed=s)
            ag = make_agent(agent, np.random.default_rng(s), task, checkpoint=checkpoint)
            ag.reset(env, obs, info)
            ep = env.episode
            traj = [env.home.world.pose[:2].copy()]
            frames, sound = [], []
            total, done = 0.0, False
            while not done:
                check_stopped()  # a SIGTERM whose raise something swallowed (a cache's except Exception) stops here
                a = ag.act(obs, info)
                obs, r, term, trunc, info = env.step(a)
                total += r
                traj.append(env.home.world.pose[:2].copy())
                if video:
                    frames.append(obs["rgb"] if "rgb" in obs else env.render())
                    sound.append(env.last_audio)
                done = term or trunc
            m = info["metrics"]
            row = {"episode": i, "episode_id": ep.episode_id, "scene": ep.scene, "category": ep.category,
                   "object": ep.object_name, "sound": ep.sound, "sound_seconds": round(ep.sound_seconds, 3),
                   "reward": round(total, 4), **{k: m[k] for k in CSV_FIELDS if k in m}}
            if maps:
                _write_map(env, ep, np.array(traj), Path(maps) / f"episode_{i:04d}.png", m)
            if video:
                _write_video(Path(video) / f"episode_{i:04d}", frames, sound, env.cfg.sample_rate)
            report(i, row)
    finally:
        env.close()


def _job(queue, j: int, threads: int, indices, play, args) -> None:
    """One job of :func:`_play_in_jobs` (a spawned process): its rows go back one by one, then ("done", j), or
    ("error", j, error class name, message)."""
    from sonicverse_core.tasks import exit_with_parent, limit_threads

    exit_with_parent()
    limit_threads(threads)
    try:
        import torch

        torch.set_num_threads(threads)
        play(indices, *args, report=lambda i, row: queue.put(("row", i, row)))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises it there
        queue.put(("error", j, type(exc).__name__, str(exc).strip().splitlines()[0] if str(exc).strip() else
                   type(exc).__name__))
        return
    queue.put(("done", j))


def _play_in_jobs(indices, jobs: int, play, args, report, desc: str, bar: bool = False) -> None:
    """Play ``indices`` with ``play`` in ``jobs`` spawned processes (each its own env, GL context and agent), calling
    ``report(i, row)`` here as each episode ends. A job that fails or dies stops the others, and its error is
    raised here."""
    import multiprocessing as mp

    from sonicverse_core.progress import progress
    from sonicverse_core.tasks import worker_threads

    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    procs = [ctx.Process(target=_job, args=(q, j, worker_threads(jobs), indices[j::jobs], play, args), daemon=True)
             for j in range(jobs)]
    for p in procs:
        p.start()
    try:
        for i, row in progress(_arrivals(q, procs), total=len(indices), desc=f"{desc} ({jobs} jobs)", enabled=bar):
            report(i, row)
    finally:
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            p.join(timeout=10)
        q.close()


def _arrivals(q, procs):
    """Yield (episode, row) from the jobs' queue until every job is done; raise a job's error here."""
    import queue as queues

    from sonicverse_core import errors

    done = set()
    while len(done) < len(procs):
        try:
            msg = q.get(timeout=1.0)
        except queues.Empty:
            dead = [j for j, p in enumerate(procs) if j not in done and p.exitcode is not None]
            if dead and q.empty():
                raise errors.SonicverseError(f"job {dead[0]} died (exit code {procs[dead[0]].exitcode})"
                                             " before its episodes were played")
            continue
        if msg[0] == "row":
            yield msg[1], msg[2]
        elif msg[0] == "done":
            done.add(msg[1])
        else:
            _, j, name, text = msg
            if name == "KeyboardInterrupt":
                raise KeyboardInterrupt
            cls = getattr(errors, name, None)
            if isinstance(cls, type) and issubclass(cls, errors.SonicverseError):
                raise cls(text)
            raise errors.SonicverseError(f"job {j} failed: {name}: {text}")


def _summary(rows, task, agent, split, sounds, seed, first, csv_path) -> dict:
    from sonicverse_core.tasks.metrics import mean_ci95, rate_ci95

    out = {"task": task, "agent": agent, "episodes": len(rows), "first": first, "split": split, "sounds": sounds,
           "seed": seed}
    for key, col in (("sr", "success"), ("spl", "spl"), ("sna", "sna"), ("soft_spl", "soft_spl"),
                     ("distance_to_goal", "distance_to_goal")):
        out[key] = (rate_ci95 if key == "sr" else mean_ci95)(r[col] for r in rows)
    out["collisions_per_episode"] = float(np.mean([r["collisions"] for r in rows]))
    out["steps_per_episode"] = float(np.mean([r["steps"] for r in rows]))
    if csv_path:
        out["csv"] = str(csv_path)
    return out


def _write_map(env, ep, traj, out: Path, m: dict) -> None:
    from sonicverse_core.scene.topdown import draw_map

    out.parent.mkdir(parents=True, exist_ok=True)
    goals = np.array(ep.goals)
    markers = {"start": (ep.start[0], ep.start[1], "g^"), "end": (traj[-1, 0], traj[-1, 1], "ks")}
    for k, g in enumerate(goals):
        markers[f"goal {k}" if k == 0 else f" {k}"] = (g[0], g[1], "r*" if k == 0 else "r.")
    title = (f"{ep.episode_id}: {ep.category} ({ep.object_name}), success {int(m['success'])}, SPL {m['spl']:.2f}, "
             f"SNA {m['sna']:.2f}")
    draw_map(env.home.scene, out, grid=env.home.world.grid, paths=[traj], markers=markers, title=title)


def _write_video(folder: Path, frames: list, sound: list, sample_rate: int) -> None:
    """Frames as numbered PNGs and the binaural audio the agent heard as a WAV (mux with ffmpeg if wanted)."""
    import soundfile as sf
    from PIL import Image

    folder.mkdir(parents=True, exist_ok=True)
    for k, f in enumerate(frames):
        if f is not None:
            Image.fromarray(f).save(folder / f"frame_{k:04d}.png")
    if sound:
        sf.write(folder / "audio.wav", np.concatenate(sound, axis=1).T, sample_rate, subtype="FLOAT")
