"""`sonicverse eval` and `sonicverse bench env`."""
from __future__ import annotations

import json
import sys

from app.cli import args as A


def cmd_eval(a) -> int:
    from app.tasks.evaluate import run_eval

    csv_path = a.csv or f"out/eval/{a.task}_{a.agent}_{a.split}_{a.sounds}_s{a.seed}.csv"
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
                   maps=a.maps, video=a.video, env_kwargs=kw, progress=progress)
    if a.json:
        print(json.dumps(res))
    else:
        for k in ("sr", "spl", "sna", "distance_to_goal"):
            lo, hi = res[k]["ci95"]
            ci = f"[{lo:.3f}, {hi:.3f}]" if lo is not None else "[n/a]"
            print(f"{k:>16}: {res[k]['mean']:.3f}  95% CI {ci}")
        print(f"per-episode CSV: {res['csv']}")
    return 0


def cmd_bench_env(a) -> int:
    from app.bench.env import bench_env

    print(json.dumps(bench_env(a.task, a.steps, a.workers, a.size, a.seed)))
    return 0


def add_task_commands(sub, bench_sub) -> None:
    from app.tasks.evaluate import TASK_NAMES

    e = sub.add_parser("eval", help="evaluate an agent on a navigation task (SR, SPL, SNA)",
                       description="Run an agent over N episodes; print SR, SPL, SNA and distance to goal with 95% "
                       "confidence intervals; write a per-episode CSV.")
    e.add_argument("--task", required=True, choices=TASK_NAMES, help="the navigation task")
    e.add_argument("--agent", required=True, choices=("random", "oracle", "gan"), help="the agent to score")
    e.add_argument("--episodes", type=A.count(1, 100_000), default=20, help="number of episodes (default: %(default)s)")
    e.add_argument("--split", default="test", choices=("train", "val", "test"), help="homes (default: %(default)s)")
    e.add_argument("--sounds", default="heard", choices=("heard", "unheard"), help="sound set (default: heard)")
    e.add_argument("--seed", type=A.seed, default=0, help="episode seed (default: %(default)s)")
    e.add_argument("--homes", type=A.count(1, 1000), default=None, help="use the first N homes of the split")
    e.add_argument("--max-steps", type=A.count(1, 100_000), default=None, help="episode length limit (default: 500)")
    e.add_argument("--csv", default=None, type=A.out_file(".csv"), help="per-episode CSV (default: out/eval/TASK_AGENT_SPLIT_SOUNDS_sSEED.csv)")
    e.add_argument("--maps", default=None, metavar="DIR", type=A.out_dir, help="write a top-down trajectory map per episode")
    e.add_argument("--video", default=None, metavar="DIR", type=A.out_dir, help="write frames (PNG) + audio (WAV) per episode")
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.set_defaults(func=cmd_eval)

    b = bench_sub.add_parser("env", help="environment steps/s: one env and N workers, with a breakdown")
    b.add_argument("--task", default="AudioGoal", choices=TASK_NAMES, help="task (default: %(default)s)")
    b.add_argument("--steps", type=A.count(10, 1_000_000), default=400, help="steps to time (default: %(default)s)")
    b.add_argument("--workers", type=A.count(0, 64), default=2,
                   help="vectorised workers (0: skip; default: %(default)s)")
    b.add_argument("--size", type=A.count(16, 2048), default=128, help="camera width = height (default: %(default)s)")
    b.add_argument("--seed", type=A.seed, default=0, help="episode seed (default: %(default)s)")
    b.add_argument("--json", action="store_true", help="(always JSON)")
    b.set_defaults(func=cmd_bench_env)
