"""`sonicverse study report`: per-participant and per-condition summaries (JSON and CSV) and plots: the orientation
task's learning curves (azimuth error per trial, a line per participant and condition), the robot's distance to
the person over time in speaker following, retrieval success per condition. A plot with no data is left out and
the summary says so."""
from __future__ import annotations

import csv
import io
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from sonicverse_core.errors import StudyError

# the figures summarised per task (rates get Wilson intervals)
KEYS = {
    "orientation-training": (("azimuth_error_deg", False), ("elevation_error_deg", False), ("reversal", True),
                             ("correct", True), ("response_time_s", False), ("walk_success", True)),
    "speaker-following": (("time_in_band", False), ("catch_success", True), ("mean_distance_m", False),
                          ("collisions", False)),
    "voice-retrieval": (("success", True), ("spl", False), ("command_accuracy", True), ("time_s", False)),
}


def _summ(rows: list[dict]) -> dict:
    from sonicverse_core.tasks.metrics import mean_ci95, rate_ci95

    out = {}
    task = rows[0]["task"]
    for key, rate in KEYS.get(task, ()):
        vals = [r["metrics"].get(key) for r in rows if r["metrics"].get(key) is not None]
        if not vals:
            continue
        out[key] = rate_ci95([bool(v) for v in vals]) if rate else mean_ci95([float(v) for v in vals])
    out["trials"] = len(rows)
    return out


def _save(fig, out: Path, name: str, summary: dict) -> None:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(out / f"{name}.png", dpi=100)
    plt.close(fig)
    summary["plots"][name] = str(out / f"{name}.png")


def write_report(store, out: str | Path, pid: str | None = None) -> dict:
    from sonicverse_core.storage import write_text_atomic

    trials = [t for t in store.trials(pid) if not t["practice"]]
    if not trials:
        who = f"participant '{pid}'" if pid else "this data folder"
        raise StudyError(f"no finished trials for {who} in {store.root}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    per_part: dict = defaultdict(lambda: defaultdict(list))
    per_cond: dict = defaultdict(list)
    for t in trials:
        per_part[t["participant"]][(t["task"], t["condition"])].append(t)
        per_cond[(t["task"], t["condition"])].append(t)
    summary = {"participants": {p: {f"{k[0]}/{k[1]}": _summ(v) for k, v in d.items()} for p, d in per_part.items()},
               "conditions": {f"{k[0]}/{k[1]}": _summ(v) for k, v in per_cond.items()},
               "plots": {}, "left_out": []}
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["participant", "task", "condition", "metric", "mean", "ci95_low", "ci95_high", "n"])
    for p, d in summary["participants"].items():
        for tc, s in d.items():
            for k, v in s.items():
                if isinstance(v, dict):
                    w.writerow([p, *tc.split("/"), k, v["mean"], *(v["ci95"] or [None, None]), v["n"]])
    write_text_atomic(out / "summary_per_participant.csv", buf.getvalue())

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    orient = [t for t in trials if t["task"] == "orientation-training" and "azimuth_error_deg" in t["metrics"]]
    if orient:
        fig, ax = plt.subplots(figsize=(7, 4))
        lines = defaultdict(list)
        for t in orient:
            lines[(t["participant"], t["condition"])].append(t["metrics"]["azimuth_error_deg"])
        for (p, c), ys in sorted(lines.items()):
            ax.plot(np.arange(1, len(ys) + 1), ys, marker="o", label=f"{p} {c}")
        ax.set(xlabel="trial (in the condition)", ylabel="azimuth error (deg, reversals resolved)",
               title="Orientation training: learning curves")
        ax.legend(fontsize=7)
        _save(fig, out, "learning_curves", summary)
    else:
        summary["left_out"].append("learning_curves (no orientation trials)")

    follow = [t for t in trials if t["task"] == "speaker-following" and t["raw"].get("trajectory")]
    if follow:
        fig, ax = plt.subplots(figsize=(7, 4))
        for t in follow:
            with np.load(store.root / t["raw"]["trajectory"]) as z:
                if len(z["distance"]):
                    ax.plot(z["t"][:len(z["distance"])], z["distance"], lw=1,
                            label=f"{t['participant']} s{t['session']} {t['condition']} #{t['trial']}")
        ax.axhspan(1.0, 2.5, color="g", alpha=0.1, label="band 1.0-2.5 m")
        ax.set(xlabel="time (s)", ylabel="geodesic distance to the person (m)", title="Speaker following")
        ax.legend(fontsize=7)
        _save(fig, out, "following_distance", summary)
    else:
        summary["left_out"].append("following_distance (no speaker-following trials)")

    retr = [t for t in trials if t["task"] == "voice-retrieval"]
    if retr:
        conds = sorted({t["condition"] for t in retr})
        rates = [np.mean([bool(t["metrics"].get("success")) for t in retr if t["condition"] == c]) for c in conds]
        fig, ax = plt.subplots(figsize=(5, 4))
        ax.bar(conds, rates)
        ax.set(ylim=(0, 1), ylabel="success rate", title="Voice retrieval per condition")
        _save(fig, out, "retrieval_success", summary)
    else:
        summary["left_out"].append("retrieval_success (no voice-retrieval trials)")
    write_text_atomic(out / "summary.json", json.dumps(summary, indent=1))
    summary["summary"] = str(out / "summary.json")
    return summary
