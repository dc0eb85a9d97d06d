"""`sonicverse study`: the human-study launcher (a PyQt6 window) and its commands (run, resume, export, report),
so studies can run headless with the simulated participant in tests and pilots."""
from __future__ import annotations

import json
import sys

from app.cli import args as A


def _progress(json_out: bool):
    def on_event(kind, p):
        if json_out:
            return
        if kind == "trial_done":
            m = p["metrics"]
            fig = next((f"{k} {m[k]:.3g}" for k in ("azimuth_error_deg", "time_in_band", "success", "walk_success")
                        if isinstance(m.get(k), (int, float))), "")
            print(f"  [{p['slot'] + 1}/{p['total']}] block {p['block']} ({p['block_name']}, {p['condition']}) "
                  f"trial {p['trial']}{' practice' if p['practice'] else ''}: {p['status']} {fig}",
                  file=sys.stderr)
        elif kind == "break":
            print(f"  break ({p['seconds']:g} s): press Enter to go on", file=sys.stderr)
    return on_event


def _run(store, study, pid, session, backend, audio_device, json_out) -> int:
    from app.study.runner import Controls, StudyRunner

    controls = Controls()

    def on_event(kind, p):
        _progress(json_out)(kind, p)
        if kind == "break":  # a person at a terminal: Enter ends the break
            try:
                input()
            except EOFError:
                pass
            controls.resume()

    res = StudyRunner(store, study, pid, session, backend, controls, on_event, audio_device).run()
    res["data"] = str(store.root)
    res["csv"] = str(store.csv_path(pid, session))
    if json_out:
        print(json.dumps(res))
    else:
        print(f"participant {pid} session {session}: {res['trials']} trials, condition order "
              f"{' -> '.join(res['order'])}; data in {store.root}")
        for f in res["quality_flags"]:
            print(f"warning: {f}", file=sys.stderr)
    return 0


def cmd_study_run(a) -> int:
    from app.study.runner import start_session
    from app.study.spec import load_study
    from app.study.store import StudyStore

    study = load_study(a.study)
    store = StudyStore(a.data)
    backend = a.backend
    simulated = a.simulated_participant or backend == "headless"
    n = start_session(store, study, a.participant, backend, simulated, a.audio_device)
    return _run(store, study, a.participant, n, backend, a.audio_device, a.json)


def cmd_study_resume(a) -> int:
    from app.study.spec import load_study
    from app.study.store import StudyStore
    from sonicverse_core.errors import StudyError

    store = StudyStore(a.data, create=False)
    store.participant(a.participant)
    s = store.session(a.participant, a.session) if a.session else store.unfinished(a.participant)
    if s is None:
        raise StudyError(f"participant '{a.participant}' has no unfinished session; start the next one with "
                         f"`sonicverse study run STUDY --participant {a.participant}`")
    if s["status"] == "finished":
        raise StudyError(f"session {s['session']} of '{a.participant}' is finished; nothing to resume")
    study = load_study(store.session_dir(a.participant, s["session"]) / "study.toml")
    return _run(store, study, a.participant, s["session"], s["backend"], a.audio_device, a.json)


def cmd_study_export(a) -> int:
    from app.study.store import StudyStore

    store = StudyStore(a.data, create=False)
    if a.participant:
        store.participant(a.participant)
    keys = ("participant", "session", "block", "block_name", "trial", "condition", "task", "practice", "status",
            "metrics", "quality", "raw", "t_mono", "t_wall", "started_wall", "duration_s")
    trials = [{k: t[k] for k in keys} for t in store.trials(a.participant, status=None)]
    out = {"trials": trials}
    if a.participant:
        out["sessions"] = [{k: s[k] for k in ("session", "study", "status", "backend", "created_wall",
                                              "finished_wall")} | {"order": json.loads(s["order_json"])}
                           for s in store.sessions(a.participant)]
        out["events"] = store.events(a.participant)
    if a.json:
        print(json.dumps(out))
    else:
        for t in trials:
            print(f"{t['participant']} s{t['session']} b{t['block']} t{t['trial']} {t['condition']:<10} "
                  f"{t['task']:<22} {t['status']}")
    return 0


def cmd_study_report(a) -> int:
    from app.study.report import write_report
    from app.study.store import StudyStore

    store = StudyStore(a.data, create=False)
    if a.participant:
        store.participant(a.participant)
    res = write_report(store, a.out, a.participant)
    if a.json:
        print(json.dumps(res))
    else:
        print(f"summary: {res['summary']}")
        for k, v in res["plots"].items():
            print(f"{k}: {v}")
    return 0


def cmd_study_window(a) -> int:
    from app.study.window import run_window

    return run_window(a.data, a.study)


def add_study_commands(sub) -> None:
    s = sub.add_parser("study", help="the human-study launcher (window) and its commands",
                       description="Without a command: open the launcher window. Studies run participants through "
                       "counterbalanced sessions of the VR tasks; every trial is committed to SQLite when it ends.")
    s.add_argument("--data", default="study-data", type=A.out_dir, help="data folder (default: ./study-data)")
    s.add_argument("--study", default="default", help="study file for the window (default: the shipped study)")
    s.set_defaults(func=cmd_study_window)
    ss = s.add_subparsers(dest="study_cmd", metavar="{run,resume,export,report}")

    def common(p):
        p.add_argument("--data", default="study-data", type=A.out_dir, help="data folder (default: ./study-data)")
        p.add_argument("--json", action="store_true", help="print one JSON object")

    r = ss.add_parser("run", help="run a new session for a participant",
                      description="Start the participant's next session (enrolling them if new) and run it. Refuses "
                      "while they have an unfinished session (see `study resume`).")
    r.add_argument("study", metavar="STUDY", help="'default' (ships with the project) or a study file (.toml)")
    r.add_argument("--participant", required=True, help="pseudonymous participant id")
    r.add_argument("--backend", default="headless", choices=("headless", "desktop", "openvr"),
                   help="headless (simulated participant; default), desktop or openvr (a person)")
    r.add_argument("--simulated-participant", action="store_true",
                   help="the listener model and simulated person of the task modules (headless)")
    r.add_argument("--audio-device", default=None, help="PortAudio device for desktop/openvr sessions")
    common(r)
    r.set_defaults(func=cmd_study_run)

    rs = ss.add_parser("resume", help="continue an unfinished session at its first unfinished trial",
                       description="Continue the participant's unfinished session (or --session N) with the same "
                       "frozen plan; the resume is logged.")
    rs.add_argument("--participant", required=True, help="participant id")
    rs.add_argument("--session", type=A.count(1, 10**6), default=None, help="session number (default: unfinished)")
    rs.add_argument("--audio-device", default=None, help="PortAudio device for desktop/openvr sessions")
    common(rs)
    rs.set_defaults(func=cmd_study_resume)

    e = ss.add_parser("export", help="print every completed trial",
                      description="Print {\"trials\": [...]}: every committed trial with participant, session, "
                      "block, trial, condition, metrics, t_mono, t_wall.")
    e.add_argument("--participant", default=None, help="one participant (default: all)")
    common(e)
    e.set_defaults(func=cmd_study_export)

    rp = ss.add_parser("report", help="summaries and plots per participant and per condition")
    rp.add_argument("--participant", default=None, help="one participant (default: all)")
    rp.add_argument("--out", required=True, type=A.out_dir, help="output folder")
    common(rp)
    rp.set_defaults(func=cmd_study_report)
