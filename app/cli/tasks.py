"""`sonicverse eval` and `sonicverse bench env`."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from app.cli import args as A


def cmd_eval(a) -> int:
    from app.tasks.evaluate import csv_name, run_eval

    csv_path = a.csv or Path("out/eval") / csv_name(a.task, a.agent, a.split, a.seed, a.first, a.sounds)
    kw = {}
    if a.homes is not None:
        kw["homes"] = a.homes
    if a.max_steps is not None:
        kw["max_steps"] = a.max_steps

    def progress(i, row):  # a line per episode where no terminal shows the bar
        if not a.json and not sys.stderr.isatty():
            print(f"episode {i}: {row['category']:<16} success {int(row['success'])} spl {row['spl']:.2f} "
                  f"sna {row['sna']:.2f} steps {row['steps']}", file=sys.stderr)

    res = run_eval(a.task, a.agent, a.episodes, split=a.split, sounds=a.sounds, seed=a.seed, csv_path=csv_path,
                   maps=a.maps, video=a.video, env_kwargs=kw, progress=progress, checkpoint=a.checkpoint,
                   first=a.first, jobs=a.jobs, resume=a.resume, overwrite=a.overwrite)
    if a.json:
        print(json.dumps(res))
    else:
        for k in ("sr", "spl", "sna", "distance_to_goal"):
            lo, hi = res[k]["ci95"]
            ci = f"[{lo:.3f}, {hi:.3f}]" if lo is not None else "[n/a]"
            print(f"{k:>16}: {res[k]['mean']:.3f}  95% CI {ci}")
        print(f"per-episode CSV: {res['csv']}")
    return 0


def cmd_train(a) -> int:
    import os

    from sonicverse_core.errors import ConfigError

    if a.unpack:
        return _unpack_ensemble(a)
    if a.ensemble:
        return _train_ensemble(a)
    if a.temperature is not None:
        from sonicverse_core.errors import ConfigError

        raise ConfigError("--temperature is an ensemble's acting setting: give it with --ensemble")
    policy = a.agent in ("av-nav", "savi", "multitask")  # the learned navigators (not the sound localiser)
    if a.teacher != "oracle" and not (a.recipe == "dagger" and policy and a.task in (
            ("AudioGoal", "SemanticAudioNav") if a.map == "route" else
            ("SpeakerFollowing", "SemanticAudioNav") if a.map else ("AudioGoal", "SemanticAudioNav"))):
        raise ConfigError("--teacher scripted is for --recipe dagger --agent av-nav|savi|multitask: with --map on "
                          "SpeakerFollowing|SemanticAudioNav, --map route or no map on AudioGoal|SemanticAudioNav "
                          "(sem-nav)")
    if a.learner != "greedy" and a.recipe != "dagger":
        raise ConfigError("--learner is for --recipe dagger (PPO's learner always draws its actions)")
    if a.map and (a.recipe != "dagger" or not policy
                  or a.task not in ("SpeakerFollowing", "AudioGoal", "SemanticAudioNav")):
        raise ConfigError("--map is for --recipe dagger --agent av-nav|savi|multitask --task SpeakerFollowing|"
                          "AudioGoal|SemanticAudioNav")
    if a.resume and a.recipe == "ppo":
        raise ConfigError("--resume is for --recipe dagger (a PPO run starts from --init)")
    if a.recipe == "ppo" and (a.jobs > 1 or a.dataset_frames != 60_000):
        raise ConfigError("--jobs and --dataset-frames belong to --recipe dagger (PPO: --envs and --nproc)")
    if a.recipe != "ppo" and (a.nproc > 1 or a.init):
        raise ConfigError("--nproc and --init belong to --recipe ppo (DD-PPO fine-tuning)")
    if a.recipe != "ppo" and (a.val_every != 20 or a.critic_warmup != 10 or a.lr is not None):
        raise ConfigError("--val-every, --critic-warmup and --lr belong to --recipe ppo (DAgger validates every "
                          "iteration at its own rate)")
    if a.recipe == "ppo" and a.agent in ("savi", "multitask") and not a.init:
        raise ConfigError(f"{a.agent} is fine-tuned by PPO from its imitation: give --init best.pt")
    if a.nproc > 1 and "LOCAL_RANK" not in os.environ:  # launch the processes, as torchrun would
        import subprocess

        argv = ["--recipe", "ppo", "--agent", a.agent, "--task", a.task, "--frames", str(a.frames), "--envs",
                str(a.envs), "--size", str(a.size), "--val-episodes", str(a.val_episodes), "--seed", str(a.seed),
                "--head", a.head, "--out", a.out, "--preempt", str(a.preempt), "--kl-init", str(a.kl_init),
                "--val-every", str(a.val_every), "--critic-warmup", str(a.critic_warmup), "--device", a.device]
        argv += ["--lr", str(a.lr)] if a.lr is not None else []
        argv += (["--init", a.init] if a.init else []) + (["--homes", str(a.homes)] if a.homes else [])
        argv += ["--json"] if a.json else []
        cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={a.nproc}",
               "-m", "agents.train", *argv]
        return subprocess.run(cmd).returncode

    def progress(row):
        if not a.json:
            print(" ".join(f"{k} {v}" for k, v in row.items()), file=sys.stderr)

    if a.agent == "sound-localizer":  # GanLocalizerAgent's localiser (supervised, not a policy)
        from agents.localizer import LocalizerTrainConfig, train as train_localizer

        if a.recipe != "dagger" or a.resume or a.homes or a.jobs > 1 or a.dataset_frames != 60_000:
            raise ConfigError("the sound localiser is trained by supervision: no --recipe ppo, --resume, --homes, "
                              "--jobs or --dataset-frames")
        if a.task == "SpeakerFollowing":
            raise ConfigError("the sound localiser learns sounding objects' places: --task AudioGoal or "
                              "SemanticAudioNav")
        cfg = LocalizerTrainConfig(task=a.task, frames=a.frames, val_frames=max(a.frames // 10, 50),
                                   epochs=a.epochs or 12, seed=a.seed)
        res = train_localizer(cfg, a.out, progress=progress)
    elif a.recipe == "ppo":
        from agents.ppo import PPOConfig, train as train_ppo

        cfg = PPOConfig(task=a.task, frames=a.frames, envs=a.envs, size=a.size, val_episodes=a.val_episodes,
                        seed=a.seed, init=a.init, head=a.head, preempt=a.preempt, kl_init=a.kl_init, device=a.device,
                        homes=a.homes or 0, val_every=a.val_every, critic_warmup=a.critic_warmup,
                        **({} if a.lr is None else {"lr": a.lr}))
        res = train_ppo(cfg, a.out, progress=progress)
        if res["rank"] != 0:
            return 0
    else:
        from agents.imitation import train

        base = None
        if a.resume:  # what the command line gives when a flag is left out: not a setting that would be dropped
            from app.cli import build_parser

            base = _imitation_config(build_parser().parse_args(["train"]))
        res = train(_imitation_config(a), a.out, progress=progress, resume=a.resume, base=base)
    print(json.dumps(res) if a.json else res["checkpoint"])
    return 0


def _imitation_config(a):
    from agents.imitation import ImitationConfig

    return ImitationConfig(task=a.task, agent=a.agent, memory=a.memory, frames=a.frames, iterations=a.iterations,
                           size=a.size, val_episodes=a.val_episodes, seed=a.seed, head=a.head,
                           aux_weight=a.aux_weight, epochs=a.epochs or 4, seq=a.seq, device=a.device,
                           homes=a.homes or 0, egomap=bool(a.map), route=a.map == "route", teacher=a.teacher,
                           learner=a.learner, jobs=a.jobs, dataset_frames=a.dataset_frames)


def cmd_bench_env(a) -> int:
    from app.bench.env import bench_env

    print(json.dumps(bench_env(a.task, a.steps, a.workers, a.size, a.seed)))
    return 0


def cmd_bench_train(a) -> int:
    from app.bench.train import bench_train

    print(json.dumps(bench_train(a.task, a.steps, tuple(a.workers), a.size, a.seed, tuple(a.agents),
                                 tuple(a.devices), a.update_batches, a.update_sequences)))
    return 0


def cmd_bench_camera(a) -> int:
    from app.bench.camera import bench_camera

    print(json.dumps(bench_camera(a.scene, a.size, a.frames, a.seed)))
    return 0


def _train_ensemble(a) -> int:
    """``train --ensemble A.pt B.pt ...``: no training; the checkpoints as one policy in --out/best.pt."""
    from pathlib import Path

    from agents.models import write_ensemble
    from sonicverse_core.errors import ConfigError

    if (a.resume or a.init or a.recipe != "dagger" or a.agent != "av-nav" or a.map or a.teacher != "oracle"
            or a.learner != "greedy"):
        raise ConfigError("--ensemble joins trained av-nav checkpoints as they are: no --resume, --init, --recipe "
                          "ppo, --agent, --map, --teacher or --learner")
    out = Path(a.out) / "best.pt"
    if out.exists():
        raise ConfigError(f"{out} exists: give another --out")
    meta = write_ensemble(a.ensemble, out, half=True, task=a.task,
                          temperature=1.0 if a.temperature is None else a.temperature)
    res = {"checkpoint": str(out), "members": meta["members"], "task": a.task, "temperature": meta["temperature"],
           "bytes": out.stat().st_size}
    print(json.dumps(res) if a.json else res["checkpoint"])
    return 0


def _unpack_ensemble(a) -> int:
    """``train --unpack ENSEMBLE.pt``: no training; each member as its own checkpoint, --out/member{k}.pt."""
    from agents.models import unpack_ensemble
    from sonicverse_core.errors import ConfigError

    if a.ensemble or a.init or a.resume or a.map or a.temperature is not None or a.recipe != "dagger":
        raise ConfigError("--unpack writes an ensemble's members as they are: no training flags")
    paths = unpack_ensemble(a.unpack, a.out)
    print(json.dumps({"members": paths}) if a.json else "\n".join(paths))
    return 0


def cmd_train_recogniser(a) -> int:
    from agents.voice import WEIGHTS, train

    def progress(i, n):  # a line at each quarter of the synthesis (the epochs are logged with --verbose)
        if i in {n // 4, n // 2, 3 * n // 4, n}:
            print(f"synthesised {i}/{n} utterances", file=sys.stderr)

    res = train(a.seed, a.epochs, a.per_class, a.out or WEIGHTS, progress=progress)
    print(json.dumps(res) if a.json else f"weights: {res['weights']} ({res['utterances']} utterances, "
          f"final training accuracy {res['history'][-1]['train_accuracy']:.3f})")
    return 0


def cmd_bench_recogniser(a) -> int:
    from app.bench.recogniser import bench_recogniser

    print(json.dumps(bench_recogniser(a.commands, a.seed, a.homes, not a.no_baseline)))
    return 0


def cmd_task_list(a) -> int:
    from sonicverse_core.tasks.registry import TASKS

    rows = [{"task": s.cli, "name": s.name, "kind": s.kind, "env_id": s.env_id, "agents": list(s.agents),
             "metrics": list(s.metrics), "summary": s.summary} for s in TASKS.values()]
    if a.json:
        print(json.dumps(rows))
    else:
        for r in rows:
            print(f"{r['task']:<22} {r['kind']:<9} agents: {', '.join(r['agents']):<22} {r['summary']}")
    return 0


def cmd_task_run(a) -> int:
    from app.tasks.run import run_task
    from sonicverse_core.tasks.registry import task_spec

    spec = task_spec(a.name)
    if a.backend != "headless":  # the user is the person, in the VR app
        from app.tasks.run import run_in_vr
        from sonicverse_core.errors import ConfigError

        for flag, v in (("--first", a.first), ("--jobs", a.jobs > 1), ("--resume", a.resume)):
            if v:
                raise ConfigError(f"{flag} is for headless runs (the robot's episodes), not --backend {a.backend}")
        res = run_in_vr(spec.name, a.agent, a.episodes, split=a.split, seed=a.seed, backend=a.backend, out=a.out,
                        trials=a.trials or 10, mode=a.mode if a.mode != "mixed" else "turn",
                        hrtf=a.hrtf == "on", reverb=a.reverb == "on", scene=a.scene, overwrite=a.overwrite)
        print(json.dumps(res) if a.json else "\n".join(f"{k:>26}: {v['mean']}" for k, v in res.items()
                                                       if isinstance(v, dict) and "mean" in v))
        return 0
    kw = {"hrtf": a.hrtf == "on", "reverb": a.reverb == "on"}
    if a.scene is not None:
        kw["scenes"] = (a.scene,)
    if a.homes is not None:
        kw["homes"] = a.homes
    if a.max_steps is not None:
        kw["max_steps"] = a.max_steps
    participant, task_kw = {}, {}
    if spec.kind == "trials":
        participant = {"noise_deg": a.noise, "front_back": a.front_back, "learning_rate": a.learning_rate}
        task_kw = {"mode": a.mode, "blocks": a.blocks, "staircase": a.staircase, "difficulty": a.difficulty,
                   "render": not a.no_render, "hrtf": a.hrtf == "on", "reverb": a.reverb == "on"}
    res = run_task(spec.name, a.agent, a.episodes, split=a.split, seed=a.seed, out=a.out, maps=a.maps,
                   env_kwargs=kw, trials=a.trials, participant=participant, task_kwargs=task_kw,
                   progress=not a.json, checkpoint=a.checkpoint, first=a.first, jobs=a.jobs, resume=a.resume,
                   overwrite=a.overwrite)
    if a.json:
        print(json.dumps(res))
    else:
        for k in spec.metrics:
            v = res[k]
            if v["mean"] is None:
                continue
            lo, hi = v["ci95"]
            ci = f"[{lo:.3f}, {hi:.3f}]" if lo is not None else "[n/a]"
            print(f"{k:>26}: {v['mean']:.3f}  95% CI {ci}  (n={v['n']})")
        if "csv" in res:
            print(f"CSV: {res['csv']}")
    return 0


def add_task_commands(sub, bench_sub) -> None:
    from sonicverse_core.tasks.registry import TASKS

    t = sub.add_parser("task", help="the task registry: list the tasks, run one with an agent",
                       description="Every task (navigation, speaker following, orientation training) and its agents.")
    ts = t.add_subparsers(dest="task_cmd", required=True, metavar="{list,run,train-recogniser}")
    tl = ts.add_parser("list", help="list the tasks, their agents and metrics")
    tl.add_argument("--json", action="store_true", help="print one JSON list")
    tl.set_defaults(func=cmd_task_list)
    clis = [s.cli for s in TASKS.values()]
    tr = ts.add_parser("run", help="run a task with an agent (headless); print its metrics with 95%% CIs",
                       description="Run N episodes (robot tasks) or trials (orientation training) and print the "
                       "task's metrics, each with a 95%% confidence interval; per-episode/per-trial CSV under --out.")
    tr.add_argument("name", choices=clis, metavar="TASK", help=f"one of {', '.join(clis)}")
    tr.add_argument("--agent", default=None,
                    help="the agent (default: the task's first; see `sonicverse task list`)")
    tr.add_argument("--checkpoint", default=None, type=A.in_file(".pt"),
                    help="a learned agent's checkpoint (default: the shipped agents/checkpoints/ARCH_TASK.pt)")
    tr.add_argument("--episodes", type=A.count(1, 100_000), default=10, help="episodes (default: %(default)s)")
    tr.add_argument("--first", type=A.count(0, 10**9), default=0,
                    help="robot tasks: start at this episode (episode i depends on --seed and i alone; default: 0)")
    tr.add_argument("--jobs", type=A.count(1, 256), default=1,
                    help="robot tasks: play the episodes in this many processes, the cores shared between them; the "
                    "same rows and metrics as one process (default: %(default)s)")
    tr.add_argument("--resume", action="store_true",
                    help="robot tasks: continue the run whose CSV is in --out (rewritten after every episode): play "
                    "only the episodes it lacks; refused if it holds another run")
    tr.add_argument("--overwrite", action="store_true",
                    help="robot tasks headless: replace a CSV in --out that this run would not repeat in full (an "
                    "interrupted run's, another run's); simulated trials: one run with other settings; desktop / "
                    "openvr: replace an earlier session's CSV; without it such a run is refused, so nothing finished "
                    "is lost")
    tr.add_argument("--trials", type=A.count(1, 1_000_000), default=None,
                    help="trials per block (orientation training; default: --episodes)")
    tr.add_argument("--split", default="test", choices=("train", "val", "test"), help="homes (default: %(default)s)")
    tr.add_argument("--seed", type=A.seed, default=0, help="seed (default: %(default)s)")
    tr.add_argument("--homes", type=A.count(1, 1000), default=None, help="use the first N homes of the split")
    tr.add_argument("--scene", default=None, metavar="SPEC", help="one home (a scene spec) instead of the split's")
    tr.add_argument("--max-steps", type=A.count(1, 100_000), default=None, help="episode length limit")
    tr.add_argument("--out", default=None, metavar="DIR", type=A.out_dir, help="write the CSV (and plots) here")
    tr.add_argument("--maps", default=None, metavar="DIR", type=A.out_dir,
                    help="write a top-down trajectory picture per episode")
    g = tr.add_argument_group("orientation training")
    g.add_argument("--mode", default="turn", choices=("turn", "walk", "mixed"), help="trial kind (default: turn)")
    g.add_argument("--blocks", type=A.count(1, 1000), default=1, help="blocks (default: %(default)s)")
    g.add_argument("--staircase", default="1up2down", choices=("1up2down", "1up3down", "none"),
                   help="adaptive staircase (default: %(default)s)")
    g.add_argument("--difficulty", default="duration", choices=("duration", "reverb", "distractor"),
                   help="what the staircase changes (default: %(default)s)")
    g.add_argument("--noise", type=A.number(0, 180, unit="degrees"), default=10.0,
                   help="simulated participant: localisation noise in degrees (default: %(default)s)")
    g.add_argument("--front-back", type=A.number(0, 1), default=0.1,
                   help="simulated participant: front-back confusion probability (default: %(default)s)")
    g.add_argument("--learning-rate", type=A.number(0, 10), default=0.0,
                   help="simulated participant: learning rate per trial (default: %(default)s)")
    g.add_argument("--no-render", action="store_true", help="do not render the stimuli (the model needs no audio)")
    tr.add_argument("--backend", default="headless", choices=("headless", "desktop", "openvr"),
                    help="headless: the Gymnasium env with the simulated person (default); desktop / openvr: the VR "
                         "app with you as the person, one session per episode")
    tr.add_argument("--hrtf", default="on", choices=("on", "off"),
                    help="off: an interaural time and level panner instead of the HRTF (default: on)")
    tr.add_argument("--reverb", default="on", choices=("on", "off"),
                    help="off: no early reflections and no late reverb (default: on)")
    tr.add_argument("--json", action="store_true", help="print one JSON object")
    tr.set_defaults(func=cmd_task_run)

    tt = ts.add_parser("train-recogniser", help="train the spoken-command recogniser (voice retrieval) from scratch",
                       description="Synthesise commands in the training voices (espeak-ng), augment them with random "
                       "rooms and noise, train the keyword classifier (torch, CPU) and write its weights (the "
                       "project ships them: agents/data/voice_commands.pt).")
    tt.add_argument("--seed", type=A.seed, default=0, help="seed (default: %(default)s)")
    tt.add_argument("--epochs", type=A.count(1, 1000), default=24, help="epochs (default: %(default)s)")
    tt.add_argument("--per-class", type=A.count(2, 100_000), default=160,
                    help="utterances per class (default: %(default)s)")
    tt.add_argument("--out", default=None, type=A.out_file(".pt"), help="weights file (default: the shipped one)")
    tt.add_argument("--json", action="store_true", help="print one JSON object")
    tt.set_defaults(func=cmd_train_recogniser)

    br = bench_sub.add_parser("recogniser", help="spoken commands at the robot's ears: ours vs pocketsphinx",
                              description="Commands in voices the recogniser was not trained on, rendered from the "
                              "person's mouth to the robot's ears in the test homes (same room, next room through "
                              "an open door); command accuracy of the keyword classifier and of pocketsphinx with "
                              "a grammar of the same commands, in the same run.")
    br.add_argument("--commands", type=A.count(1, 100_000), default=100,
                    help="commands per condition (default: %(default)s)")
    br.add_argument("--homes", type=A.count(1, 1000), default=4, help="test homes (default: %(default)s)")
    br.add_argument("--seed", type=A.seed, default=0, help="seed (default: %(default)s)")
    br.add_argument("--no-baseline", action="store_true", help="skip pocketsphinx")
    br.add_argument("--json", action="store_true", help="(always JSON)")
    br.set_defaults(func=cmd_bench_recogniser)

    from app.tasks.evaluate import TASK_NAMES

    e = sub.add_parser("eval", help="evaluate an agent on a navigation task (SR, SPL, SNA)",
                       description="Run an agent over N episodes; print SR, SPL, SNA and distance to goal with 95% "
                       "confidence intervals; write a per-episode CSV.")
    e.add_argument("--task", required=True, choices=TASK_NAMES, help="the navigation task")
    e.add_argument("--agent", required=True, metavar="AGENT",
                   help="random, oracle, gan, gan-itd, sem-nav, av-nav, savi, multitask (learned policies), or "
                   "module:callable (your own policy)")
    e.add_argument("--checkpoint", default=None, type=A.in_file(".pt"),
                   help="a learned agent's checkpoint (default: the shipped agents/checkpoints/ARCH_TASK.pt)")
    e.add_argument("--episodes", type=A.count(1, 100_000), default=20, help="number of episodes (default: %(default)s)")
    e.add_argument("--first", type=A.count(0, 10**9), default=0,
                   help="start at this episode: episode i depends on --seed and i alone, so a long evaluation can be "
                   "split into parts that give the rows of one run (default: %(default)s)")
    e.add_argument("--jobs", type=A.count(1, 256), default=1,
                   help="play the episodes in this many processes, the cores shared between them; the same rows and "
                   "metrics as one process (default: %(default)s)")
    e.add_argument("--split", default="test", choices=("train", "val", "test"), help="homes (default: %(default)s)")
    e.add_argument("--sounds", default="heard", choices=("heard", "unheard"), help="sound set (default: heard)")
    e.add_argument("--seed", type=A.seed, default=0, help="episode seed (default: %(default)s)")
    e.add_argument("--homes", type=A.count(1, 1000), default=None, help="use the first N homes of the split")
    e.add_argument("--max-steps", type=A.count(1, 100_000), default=None, help="episode length limit (default: 500)")
    e.add_argument("--csv", default=None, type=A.out_file(".csv"), help="per-episode CSV (default: out/eval/TASK_AGENT_SPLIT_SOUNDS_sSEED.csv, "
                   "with _fromK for --first K: the parts of a long run do not overwrite each other)")
    e.add_argument("--maps", default=None, metavar="DIR", type=A.out_dir, help="write a top-down trajectory map per episode")
    e.add_argument("--video", default=None, metavar="DIR", type=A.out_dir, help="write frames (PNG) + audio (WAV) per episode")
    e.add_argument("--resume", action="store_true",
                   help="continue the evaluation whose CSV --csv names (it is rewritten after every episode): play "
                   "only the episodes it lacks; refused if it holds another evaluation")
    e.add_argument("--overwrite", action="store_true",
                   help="replace a CSV that this run would not repeat in full (an interrupted run's, another "
                   "evaluation's, other episodes'); without it such a run is refused, so no finished episode is lost")
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.set_defaults(func=cmd_eval)

    t = sub.add_parser("train", help="train a learned agent: imitation of the oracle (DAgger), then PPO",
                       description="--recipe dagger: behaviour cloning with DAgger on train homes and heard sounds; "
                       "--recipe ppo: PPO from --init (the imitation's best.pt), on --nproc processes (DD-PPO). "
                       "Validation SR/SPL (speaker following: catch success and time in band) on val homes; "
                       "checkpoints (model.pt, best.pt) and a CSV log (log.csv) in --out.")
    t.add_argument("--recipe", default="dagger", choices=("dagger", "ppo"), help="stage (default: %(default)s)")
    t.add_argument("--init", default=None, type=A.in_file(".pt"), help="PPO: the checkpoint to start from")
    t.add_argument("--envs", type=A.count(1, 64), default=2, help="PPO: environments per process "
                   "(default: %(default)s)")
    t.add_argument("--nproc", type=A.count(1, 256), default=1, help="PPO: processes on this machine (DD-PPO, "
                   "gloo on CPU; default: %(default)s)")
    t.add_argument("--preempt", type=A.number(0.0, 1.0, lo_open=True), default=0.6,
                   help="DD-PPO: the share of processes whose finished rollouts stop the stragglers' "
                   "(default: %(default)s)")
    t.add_argument("--kl-init", type=A.number(0.0, 100.0), default=0.1,
                   help="PPO: weight of the KL divergence from the --init policy (default: %(default)s)")
    t.add_argument("--val-every", type=A.count(1, 10**6), default=20,
                   help="PPO: updates between validations (default: %(default)s)")
    t.add_argument("--critic-warmup", type=A.count(0, 10**6), default=10,
                   help="PPO from --init: first updates that train the value head alone (default: %(default)s)")
    t.add_argument("--lr", type=A.number(1e-8, 1.0), default=None,
                   help="PPO: Adam's learning rate (default: 2.5e-5)")
    t.add_argument("--agent", default="av-nav", choices=("av-nav", "savi", "multitask", "sound-localizer"),
                   help="the model: the AV-Nav policy, SAVi, the multi-task model (SAVi + occupancy anticipation), "
                   "or the learned sound localiser of agents.scripted:GanLocalizerAgent (default: %(default)s)")
    t.add_argument("--memory", type=A.count(1, 1000), default=32,
                   help="savi / multitask: steps of scene memory (default: %(default)s)")
    t.add_argument("--task", default="AudioGoal", choices=("AudioGoal", "SemanticAudioNav", "SpeakerFollowing"),
                   help="the task (default: %(default)s)")
    t.add_argument("--frames", type=A.count(100, 10**9), default=20_000, help="environment frames (default: %(default)s)")
    t.add_argument("--iterations", type=A.count(1, 100_000), default=10, help="DAgger iterations (default: %(default)s)")
    t.add_argument("--size", type=A.count(40, 256), default=64, help="depth image side (default: %(default)s)")
    t.add_argument("--val-episodes", type=A.count(0, 10_000), default=8,
                   help="validation episodes per iteration (default: %(default)s)")
    t.add_argument("--head", default="discrete", choices=("discrete", "fine", "continuous"),
                   help="action head: wheel-velocity primitives (fine: 25 of them, finer veers) or a Gaussian mean "
                   "(default: %(default)s)")
    t.add_argument("--aux-weight", type=A.number(0.0, 100.0), default=0.5,
                   help="weight of the goal-prediction loss, 0 for none (default: %(default)s)")
    t.add_argument("--epochs", type=A.count(1, 1000), default=None, help="passes over the dataset per iteration "
                   "(default: 4; the sound localiser: 12 in all)")
    t.add_argument("--jobs", type=A.count(1, 256), default=1,
                   help="imitation: collect and validate in J spawned processes (each its own env and a copy of "
                   "the policy; the fit stays in the main process, on --device); a run is reproducible for the "
                   "same J (default: %(default)s)")
    t.add_argument("--dataset-frames", type=A.count(100, 10**8), default=60_000,
                   help="imitation: the dataset keeps the latest N frames (about 10 KB each at --size 64; "
                   "default: %(default)s)")
    t.add_argument("--seq", type=A.count(2, 10_000), default=48, help="imitation: steps per training sequence "
                   "(default: %(default)s)")
    t.add_argument("--homes", type=A.count(1, 5000), default=None,
                   help="draw training episodes from the first N train homes (default: 16)")
    t.add_argument("--map", nargs="?", const="task", choices=("task", "route"), default=None,
                   help="av-nav, savi, multitask: read an egocentric map; on "
                   "SpeakerFollowing the floor plan, the scripted follower's belief of where the person is, who the "
                   "camera saw, its route; on AudioGoal what the robot mapped itself: obstacles and floor from depth, "
                   "how loud the sound was where it stood, its track; on SemanticAudioNav that and where the "
                   "semantic camera saw the category its ears name; '--map route' (AudioGoal, SemanticAudioNav): "
                   "the semantic map and the way sem-nav would go now; trained on --teacher's actions")
    t.add_argument("--teacher", choices=("oracle", "scripted"), default="oracle",
                   help="imitation: whose actions the policy learns, the privileged oracle's or (--map on "
                   "SpeakerFollowing) the scripted follower's or (--map on SemanticAudioNav) sem-nav's, which see "
                   "what the map shows, or (AudioGoal, SemanticAudioNav without --map) sem-nav's, which act on the "
                   "robot's own sensors (default: %(default)s)")
    t.add_argument("--learner", choices=("greedy", "drawn"), default="greedy",
                   help="imitation: how the learner acts when DAgger lets it, its most likely action or drawn as it "
                   "plays (through the floor shield where it reads the floor plan) (default: %(default)s)")
    t.add_argument("--ensemble", nargs="+", type=A.in_file(".pt"), metavar="PT", default=None,
                   help="train nothing: join these av-nav checkpoints of --task (one configuration, e.g. the same "
                   "recipe from several --seed) into one policy acting on the mean of their action distributions, "
                   "written to --out/best.pt as float16")
    t.add_argument("--unpack", type=A.in_file(".pt"), metavar="PT", default=None,
                   help="train nothing: write each member of this ensemble (train --ensemble) as its own checkpoint, "
                   "--out/member0.pt, member1.pt, ...")
    t.add_argument("--temperature", type=A.number(0.05, 10), default=None,
                   help="with --ensemble: the player draws from the mean distribution raised to 1 / T (below 1, "
                   "nearer the most likely action; default 1)")
    t.add_argument("--seed", type=A.seed, default=0, help="seed (default: %(default)s)")
    t.add_argument("--out", default="out/train", type=A.out_dir, help="output folder (default: %(default)s)")
    t.add_argument("--resume", action="store_true", help="go on from --out's model.pt (to more --iterations)")
    t.add_argument("--device", default="cpu", choices=("cpu", "cuda", "auto"),
                   help="where the model acts and trains (auto: CUDA when torch sees it; default: %(default)s)")
    t.add_argument("--json", action="store_true", help="print one JSON object")
    t.set_defaults(func=cmd_train)

    b = bench_sub.add_parser("env", help="environment steps/s: one env and N workers, with a breakdown")
    b.add_argument("--task", default="AudioGoal", choices=TASK_NAMES, help="task (default: %(default)s)")
    b.add_argument("--steps", type=A.count(10, 1_000_000), default=400, help="steps to time (default: %(default)s)")
    b.add_argument("--workers", type=A.count(0, 64), default=2,
                   help="vectorised workers (0: skip; default: %(default)s)")
    b.add_argument("--size", type=A.count(16, 2048), default=128, help="camera width = height (default: %(default)s)")
    b.add_argument("--seed", type=A.seed, default=0, help="episode seed (default: %(default)s)")
    b.add_argument("--json", action="store_true", help="(always JSON)")
    b.set_defaults(func=cmd_bench_env)

    bt = bench_sub.add_parser("train", help="learned agents' rollout and update frames/s, and vector-env scaling",
                              description="Rollout frames/s of the AV-Nav policy in one env (audio + depth, audio "
                              "only) with the env's and the model's shares, the imitation update's frames/s, and "
                              "steps/s against the number of subprocess workers.")
    bt.add_argument("--task", default="AudioGoal", choices=("AudioGoal", "SemanticAudioNav"),
                    help="task (default: %(default)s)")
    bt.add_argument("--steps", type=A.count(20, 1_000_000), default=300, help="steps to time (default: %(default)s)")
    bt.add_argument("--agents", nargs="+", default=["av-nav"], choices=("av-nav", "savi", "multitask"),
                    help="models whose rollout and update to time beside each other (default: av-nav)")
    bt.add_argument("--workers", type=A.count(1, 64), nargs="+", default=[1, 2],
                    help="numbers of vector-env workers to time (default: 1 2)")
    bt.add_argument("--size", type=A.count(40, 256), default=64, help="depth image side (default: %(default)s)")
    bt.add_argument("--update-batches", type=A.count(1, 10_000), default=4,
                    help="imitation batches to time per update measurement, after one warm-up (default: %(default)s)")
    bt.add_argument("--update-sequences", type=A.count(1, 4096), default=16,
                    help="sequences of 48 steps per update batch (default: %(default)s, the imitation recipe's)")
    bt.add_argument("--devices", nargs="+", default=["cpu"], choices=("cpu", "cuda"),
                    help="devices to time the models on, side by side in the same run (default: cpu)")
    bt.add_argument("--seed", type=A.seed, default=0, help="episode seed (default: %(default)s)")
    bt.add_argument("--json", action="store_true", help="(always JSON)")
    bt.set_defaults(func=cmd_bench_train)

    bc = bench_sub.add_parser("camera", help="ms per frame of the robot camera's outputs: depth, RGB-D, semantic",
                              description="The robot's camera (depth, RGB-D, the semantic camera's category and "
                              "instance ids, RGB-D + semantic) over the same poses in one run, as ratios to depth.")
    bc.add_argument("--scene", default="builtin:apartment", help="scene spec (default: %(default)s)")
    bc.add_argument("--size", type=A.count(16, 2048), default=128, help="width = height (default: %(default)s)")
    bc.add_argument("--frames", type=A.count(10, 100_000), default=100, help="poses (default: %(default)s)")
    bc.add_argument("--seed", type=A.seed, default=0, help="seed of the poses (default: %(default)s)")
    bc.add_argument("--json", action="store_true", help="(always JSON)")
    bc.set_defaults(func=cmd_bench_camera)
