"""The study launcher's data safety and bookkeeping: balanced Latin squares, frozen orders, SQLite + CSV that survive
SIGKILL with at most the running trial lost, resume without duplicates, nothing overwritten, the default study end
to end, the study file's validation."""
import csv
import itertools
import json
import signal
import sqlite3
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from app.study.design import assign_row, session_plan, williams
from app.study.runner import StudyRunner, start_session
from app.study.spec import load_study, parse_study
from app.study.store import StudyStore
from sonicverse_core.errors import StudyError

ROOT = Path(__file__).resolve().parents[1]

SMALL = """
name = "small"
seed = 3
break_s = 5
[conditions.a]
hrtf = "on"
[conditions.b]
hrtf = "off"
simulated = { front_back = 0.4 }
[conditions.c]
reverb = "off"
[[blocks]]
name = "turns"
task = "orientation-training"
trials = 2
practice = 1
[[blocks]]
name = "follow"
task = "speaker-following"
trials = 3
agent = "scripted"
condition = "a"
time_limit_s = 10
"""


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 6, 7])
def test_williams_square_is_balanced(n):
    rows = williams(n)
    assert len(rows) == (n if n % 2 == 0 else 2 * n)
    for r in rows:
        assert sorted(r) == list(range(n))
    # every condition in every position equally often
    for pos in range(n):
        assert Counter(r[pos] for r in rows) == Counter({c: len(rows) // n for c in range(n)})
    # every condition follows every other equally often (first-order carry-over)
    if n > 1:
        pairs = Counter((r[i], r[i + 1]) for r in rows for i in range(n - 1))
        assert set(pairs) == {(a, b) for a, b in itertools.permutations(range(n), 2)}
        assert len(set(pairs.values())) == 1


def test_williams_first_row_is_the_textbook_one():
    assert williams(4)[0] == [0, 1, 3, 2]  # 1, 2, n, 3 (1-based)
    assert williams(6)[0] == [0, 1, 5, 2, 4, 3]


def test_participants_fill_the_square_in_enrolment_order(tmp_path):
    study = parse_study(SMALL)
    store = StudyStore(tmp_path)
    rows = williams(3)
    orders = []
    for i in range(2 * len(rows)):  # twice round the 6-row square
        pid = f"P{i + 1:02d}"
        n = start_session(store, study, pid)
        orders.append(store.order(pid, n))
    names = [c.name for c in study.conditions]
    for pos in range(3):
        assert Counter(o[pos] for o in orders) == Counter({c: 4 for c in names})
    assert orders[0] == [names[i] for i in rows[0]] and orders[len(rows)] == orders[0]
    # frozen: the plan and order a session was created with are read back unchanged by a new store
    again = StudyStore(tmp_path)
    assert again.order("P02", 1) == orders[1]
    assert again.plan("P02", 1) == session_plan(study, orders[1], 2, 1)


def test_least_filled_counts_completed_sessions_only(tmp_path):
    study = parse_study(SMALL.replace('seed = 3', 'seed = 3\ncounterbalance = "least-filled"'))
    store = StudyStore(tmp_path)
    start_session(store, study, "A")  # row 0, unfinished
    start_session(store, study, "B")
    assert store.session("B")["order_row"] == 0  # A's session is not completed: row 0 is still the least filled
    store.set_status("A", 1, "finished")
    start_session(store, study, "C")
    assert store.session("C")["order_row"] == 1
    assert assign_row("least-filled", 3, 99, {0: 2, 1: 1, 2: 1, 3: 1, 4: 0, 5: 1}) == 4


def test_nothing_is_overwritten(tmp_path):
    study = parse_study(SMALL)
    store = StudyStore(tmp_path)
    start_session(store, study, "P1")
    with pytest.raises(StudyError, match="study resume"):  # an unfinished session: refuse, point to resume
        start_session(store, study, "P1")
    first = store.plan("P1", 1)[0]
    store.commit_trial("P1", 1, first, "done", {"x": 0}, {}, {}, "t", 0.1)
    before = store.csv_path("P1", 1).read_bytes()
    store.set_status("P1", 1, "finished")
    assert start_session(store, study, "P1") == 2  # after a finished one: the next number
    with pytest.raises(StudyError, match="exists"):
        store.add_participant("P1")
    with pytest.raises(StudyError, match="pseudonymous"):
        store.add_participant("../etc")
    slot = store.plan("P1", 2)[0]
    store.commit_trial("P1", 2, slot, "done", {"x": 1}, {}, {}, "t", 0.1)
    with pytest.raises(sqlite3.IntegrityError):  # a slot is committed once
        store.commit_trial("P1", 2, slot, "done", {"x": 2}, {}, {}, "t", 0.1)
    assert [t["metrics"] for t in store.trials("P1", 2)] == [{"x": 1}]
    assert store.csv_path("P1", 1).read_bytes() == before and store.csv_path("P1", 2) != store.csv_path("P1", 1)
    # identifying details go to a separate file, never into the database or the session folders
    store.add_participant("P9", {"name": "Ada"})
    assert "Ada" in (tmp_path / "private" / "identities.csv").read_text()
    assert b"Ada" not in (tmp_path / "study.sqlite").read_bytes()


def test_resume_refuses_a_changed_study_file(tmp_path):
    study = parse_study(SMALL)
    store = StudyStore(tmp_path)
    n = start_session(store, study, "P1")
    with pytest.raises(StudyError, match="another version"):
        StudyRunner(store, parse_study(SMALL.replace("trials = 3", "trials = 4")), "P1", n)


@pytest.mark.parametrize("bad, match", [
    ("name = 'x y'", "name"),
    ("name = 'x'\n[conditions.a]\nhrtf = 'maybe'\n[[blocks]]\ntask = 'orientation-training'\ntrials = 1", "hrtf"),
    ("name = 'x'\n[conditions.a]\n[[blocks]]\ntask = 'audio-goal'\ntrials = 1", "no person"),
    ("name = 'x'\n[conditions.a]\n[[blocks]]\ntask = 'orientation-training'\ntrials = 0", "trials"),
    ("name = 'x'\n[conditions.a]\n[[blocks]]\ntask = 'speaker-following'\ntrials = 1\nagent = 'gan'", "agent"),
    ("name = 'x'\n[conditions.a]\n[[blocks]]\ntask = 'speaker-following'\ntrials = 1\ncondition = 'z'", "condition"),
    ("name = 'x'\n[conditions.a]\nsimulated = { front_back = 2 }\n[[blocks]]\ntask = 'orientation-training'\n"
     "trials = 1", "front_back"),
    ("name = 'x'\ncolour = 1\n[conditions.a]\n[[blocks]]\ntask = 'orientation-training'\ntrials = 1", "colour"),
    ("name = 'x'\n[conditions.a]\nhome = 'builtin:nowhere'\n[[blocks]]\ntask = 'speaker-following'\ntrials = 1",
     "home"),
    ("name = [", "TOML"),
])
def test_study_file_mistakes_are_one_line(bad, match):
    with pytest.raises(StudyError, match=match) as e:
        parse_study(bad)
    assert "\n" not in str(e.value)


def _run(*args, **kw):
    return subprocess.run([sys.executable, "-m", "app.cli", "study", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=600, **kw)


def test_default_study_runs_headless_with_report(tmp_path):
    data = tmp_path / "data"
    r = _run("run", "default", "--participant", "S1", "--data", str(data), "--json")
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    study = load_study("default")
    plan_len = sum((b.trials + b.practice) * (len(study.conditions) if b.per_condition else 1) for b in study.blocks)
    assert res["trials"] == plan_len and sorted(res["order"]) == ["hrtf", "panner"]
    ex = json.loads(_run("export", "--participant", "S1", "--data", str(data), "--json").stdout)
    assert len(ex["trials"]) == plan_len
    for t in ex["trials"]:
        assert {"participant", "session", "block", "trial", "condition", "metrics", "t_mono", "t_wall"} <= set(t)
    conds = [t["condition"] for t in ex["trials"] if t["task"] == "orientation-training"]
    assert conds[0] == res["order"][0] and conds[-1] == res["order"][1]
    # the conditions reached the renderer: the panner condition's stimuli are a time/level panner's
    man = json.loads((data / "S1" / "session-1" / "manifest.json").read_text())
    assert man["conditions"]["panner"]["hrtf"] == "off" and man["study_sha256"] == study.sha256
    assert man["packages"]["numpy"] and man["condition_order"] == res["order"]
    rep = _run("report", "--data", str(data), "--out", str(tmp_path / "rep"), "--json")
    assert rep.returncode == 0, rep.stderr
    plots = json.loads(rep.stdout)["plots"]
    assert set(plots) == {"learning_curves", "following_distance"}
    for p in plots.values():
        assert Path(p).stat().st_size > 10_000


def _csv_slots(path: Path, store, pid, n) -> list:
    plan = {(s.block, s.trial): s.slot for s in store.plan(pid, n)}
    with open(path, newline="") as fh:
        return [plan[(int(r["block"]), int(r["trial"]))] for r in csv.DictReader(fh)]


def _wait_mid_trial(proc, db: Path, min_done: int, task: str, timeout=300.0) -> int:
    """Until a trial of ``task`` has started and not ended, after ``min_done`` trials were committed (polling the
    database the run writes; the trials last seconds)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.stderr.read()
        if db.is_file():
            try:
                con = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)
                done = {r[0] for r in con.execute("SELECT slot FROM trials")}
                started = [r[0] for r in con.execute(
                    "SELECT e.slot FROM events e JOIN plan p ON p.slot = e.slot AND p.participant = e.participant "
                    "AND p.session = e.session WHERE e.kind = 'started' AND p.task = ?", (task,))]
                con.close()
                running = [s for s in started if s not in done]
                if len(done) >= min_done and running:
                    return running[-1]
            except sqlite3.OperationalError:
                pass
        time.sleep(0.02)
    proc.kill()
    pytest.fail("the study never reached a running trial")


def test_a_stop_inside_a_commit_waits_for_its_end_and_stays_noted():
    """SIGTERM's handler (errors.stop) during a trial's commit notes the stop and raises it when the commit is done
    (blocking the signal in the main thread does not hold it when other threads run); once noted, every later
    safe point raises it again, so a raise that something swallowed cannot let the study run on."""
    from sonicverse_core import errors

    try:
        done = []
        with pytest.raises(errors.Interrupted, match="SIGTERM"):
            with errors.stop_held():
                errors.stop("terminated (SIGTERM)")  # noted, not raised here
                done.append("committed")
        assert done == ["committed"]
        with pytest.raises(errors.Interrupted):
            errors.check_stopped()
    finally:
        errors._STOPPED.clear()
    errors.check_stopped()  # nothing noted: no raise


def test_a_stop_raised_in_a_finaliser_prints_nothing_and_stays_noted(monkeypatch):
    """SIGTERM's handler may run inside a __del__ (or a finaliser the collector calls), where Python cannot pass the
    raise on and hands it to sys.unraisablehook, whose default prints "Exception ignored" and a traceback: the CLI's
    one-line promise broken. Under the CLI's hook the stop reaches no printer, stays noted and is raised at the next
    check; other such errors go on to the hook as before, and the hook is put back after."""
    import sys

    from sonicverse_core import errors

    printed = []  # what Python's default hook would have printed
    monkeypatch.setattr(sys, "unraisablehook", lambda u: printed.append(type(u.exc_value).__name__))

    class Dies:
        def __init__(self, raise_):
            self.raise_ = raise_

        def __del__(self):
            self.raise_()

    def fail():
        raise KeyError("a bug in a finaliser")

    def sigterm():
        errors.stop("terminated (SIGTERM)")

    try:
        with errors.stops_quiet_in_finalisers():
            Dies(sigterm)
            assert printed == []
            with pytest.raises(errors.Interrupted, match="SIGTERM"):
                errors.check_stopped()
            Dies(fail)
            assert printed == ["KeyError"]
        Dies(sigterm)  # the hook is gone: printed again
        assert printed == ["KeyError", "Interrupted"]
    finally:
        errors._STOPPED.clear()


def test_a_stop_that_python_wrapped_aborts_the_running_trial_and_points_to_resume(tmp_path, wrapped_stop,
                                                                                 monkeypatch):
    """CI saw SIGTERM land while a trial imported its task module: the raise came wrapped in a RuntimeError, the
    running trial was not marked aborted and the last line said nothing of `study resume`."""
    from sonicverse_core.errors import Interrupted

    study = parse_study(SMALL)
    store = StudyStore(tmp_path)
    n = start_session(store, study, "W1")
    runner = StudyRunner(store, study, "W1", n)
    ran = []

    def run(slot, check):
        ran.append(slot.slot)
        if len(ran) == 2:
            wrapped_stop()
        return {"azimuth_error_deg": 1.0}, {}, {}

    monkeypatch.setattr(runner.trials, "run", run)
    with pytest.raises(Interrupted, match=r"^terminated \(SIGTERM\): the running trial was not kept; continue with "
                                          "`sonicverse study resume"):
        runner.run()
    assert sorted(store.finished_slots("W1", n)) == ran[:1]
    assert [(e["slot"], e["detail"]) for e in store.events("W1", n) if e["kind"] == "aborted"] == [
        (ran[1], "terminated (SIGTERM)")]


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_killed_in_a_trial_loses_at_most_that_trial_and_resumes(tmp_path, sig):
    study_file = tmp_path / "small.toml"
    study_file.write_text(SMALL)
    data = tmp_path / "data"
    proc = subprocess.Popen([sys.executable, "-m", "app.cli", "study", "run", str(study_file), "--participant",
                             "K1", "--data", str(data)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    running = _wait_mid_trial(proc, data / "study.sqlite", 4, "speaker-following")
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    store = StudyStore(data)
    plan = store.plan("K1", 1)
    done = sorted(store.finished_slots("K1", 1))
    assert done == list(range(len(done))) and len(done) >= 4  # in order, none lost before the running one
    # the trial seen running may have finished (and been committed) before the signal landed: then the next one ran
    first_open = len(done)
    assert first_open in (running, running + 1), (running, done)
    csv_path = data / "K1" / "session-1" / "trials.csv"
    assert _csv_slots(csv_path, store, "K1", 1) == done  # every committed trial in the CSV exactly once
    order = store.order("K1", 1)
    if sig == signal.SIGTERM:  # a clean stop: one line, the running trial marked aborted
        assert proc.returncode == 2 and err.strip().splitlines()[-1].startswith("sonicverse: error:"), err
        assert "study resume" in err and "Traceback" not in err
        aborted = [e["slot"] for e in store.events("K1", 1) if e["kind"] == "aborted"]
        assert aborted in ([first_open], []) and (aborted or first_open != running), aborted  # none: between trials
    else:
        assert proc.returncode == -signal.SIGKILL
    # a second run refuses (unfinished), resume completes with no duplicate and the same order
    r = _run("run", str(study_file), "--participant", "K1", "--data", str(data))
    assert r.returncode == 2 and "study resume" in r.stderr
    r = _run("resume", "--participant", "K1", "--data", str(data), "--json")
    assert r.returncode == 0, r.stderr
    store = StudyStore(data)
    assert sorted(store.finished_slots("K1", 1)) == [s.slot for s in plan]
    assert store.order("K1", 1) == order and store.plan("K1", 1) == plan
    assert _csv_slots(csv_path, store, "K1", 1) == [s.slot for s in plan]
    assert store.session("K1", 1)["status"] == "finished"
    follows = [t for t in store.trials("K1", 1) if t["task"] == "speaker-following"]
    assert len(follows) == 3
    for t in follows:  # the block's time_limit_s holds headless too: 10 s of 0.1 s steps
        raw = np.load(data / t["raw"]["trajectory"])
        assert len(raw["t"]) <= 101 and raw["t"][-1] <= 10.0 + 1e-9
    resumes = [e for e in store.events("K1", 1) if e["kind"] == "resume"]
    assert len(resumes) == 1 and json.loads(resumes[0]["detail"])["first_slot"] == first_open


def test_a_csv_behind_the_database_is_rewritten(tmp_path):
    """A kill between the commit and the CSV append (or in the middle of a line) leaves the CSV behind: the next
    run rewrites it from the database before going on."""
    study = parse_study(SMALL)
    store = StudyStore(tmp_path)
    n = start_session(store, study, "P1")
    for slot in store.plan("P1", n)[:3]:
        store.commit_trial("P1", n, slot, "done", {"i": slot.slot}, {}, {}, "t", 0.0)
    p = store.csv_path("P1", n)
    text = p.read_text()
    p.write_text(text[: len(text) - 20])  # the last line cut short
    assert store.reconcile_csv("P1", n)
    assert _csv_slots(p, store, "P1", n) == [0, 1, 2]
    assert not store.reconcile_csv("P1", n)


def test_hrtf_off_reaches_the_env_renderer():
    from sonicverse_core.tasks import make_env

    env = make_env("SpeakerFollowing", split="test", hrtf=False, reverb=False)
    env.reset(seed=0)
    assert env.renderer.cfg.output == "stereo" and env.renderer.hrtf is None
    assert "late_reverb" not in env.renderer.subsystems
    env.close()


def test_a_person_trial_in_the_desktop_app_on_jack(tmp_path, jack, monkeypatch):
    """A desktop session (Qt offscreen, live audio over JACK's dummy backend): the trial is a VR session whose
    missed frames, xruns and output latency are its quality figures; a person who does not answer within the
    block's time limit gives a no_response trial; the session's raw data is kept."""
    monkeypatch.setenv("QT_QPA_PLATFORM", "offscreen")
    f = tmp_path / "desk.toml"
    f.write_text('name = "desk"\n[conditions.panner]\nhrtf = "off"\n[[blocks]]\ntask = "orientation-training"\n'
                 'trials = 1\ntime_limit_s = 2\n')
    data = tmp_path / "data"
    r = _run("run", str(f), "--participant", "D1", "--backend", "desktop", "--data", str(data), "--json")
    assert r.returncode == 0, r.stderr
    store = StudyStore(data)
    (t,) = store.trials("D1", 1, status=None)
    assert t["status"] == "no_response"
    q = t["quality"]
    assert q["missed_frames"] is not None and q["xruns"] is not None and q["latency_ms"] > 0
    raw = data / t["raw"]["session"]
    assert (raw / "binaural.wav").is_file() and (raw / "input.svrec").is_file()
    man = json.loads((data / "D1" / "session-1" / "manifest.json").read_text())
    assert man["backend"] == "desktop" and man["devices"]["audio"] == "system default"


def test_condition_options_reach_the_task(cli):
    r = cli("task", "run", "orientation-training", "--trials", "2", "--hrtf", "off", "--reverb", "off", "--json")
    assert r.returncode == 0, r.stderr
    cfg = json.loads(r.stdout)["config"]
    assert cfg["hrtf"] is False and cfg["reverb"] is False
    r = cli("task", "run", "orientation-training", "--trials", "2", "--hrtf", "maybe")
    assert r.returncode == 2 and "--hrtf" in r.stderr


def test_a_trial_on_the_headset_backend(tmp_path, jack, monkeypatch):
    """The study's openvr backend through fakes of OpenVR built from pyopenvr's types (no runtime can exist here):
    the participant answers with the right controller's trigger; the trial is scored and its quality recorded."""
    sys.path.insert(0, str(Path(__file__).parent))
    from fake_openvr import install

    from app.vr.frame import BUTTON_TRIGGER

    rig = install(monkeypatch)
    for k in range(30, 600, 15):  # the trigger now and then, from the half second on
        rig.buttons[(k, 2)] = int(BUTTON_TRIGGER)
    study = parse_study('name = "hmd"\n[conditions.a]\n[[blocks]]\ntask = "orientation-training"\ntrials = 2\n'
                        'time_limit_s = 5\n')
    store = StudyStore(tmp_path)
    n = start_session(store, study, "H1", backend="openvr", simulated=False)
    StudyRunner(store, study, "H1", n, backend="openvr").run()
    rows = store.trials("H1", n, status=None)
    assert [r["status"] for r in rows] == ["done", "done"], rows
    for r in rows:
        assert 0 <= r["metrics"]["azimuth_error_deg"] <= 180 and r["metrics"]["response_time_s"] > 0
        assert r["quality"]["latency_ms"] > 0 and r["quality"]["missed_frames"] is not None
    assert rig.shutdowns == 2  # one VR session per trial, each closed
