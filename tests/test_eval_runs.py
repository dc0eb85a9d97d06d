"""Evaluation runs (app/tasks/evaluate.py, `sonicverse eval`): episodes fixed by seed and index, a CSV that a rerun
never shortens, a stopped run that keeps its episodes and resumes byte for byte, a stop inside an episode, and a
failing job's own error."""
import json
import signal
import subprocess
import sys

import pytest


def test_an_evaluations_episodes_depend_on_the_seed_and_index_alone(tmp_path):
    """README (AudioGoal over 200 episodes): episode i of a seeded evaluation is the same whatever the number of
    episodes, and a rerun repeats it step for step (the agent's Generator is seeded per episode too)."""
    import csv

    from app.tasks.evaluate import run_eval

    kw = {"max_steps": 40}
    run_eval("AudioGoal", "random", 2, seed=3, csv_path=tmp_path / "a.csv", env_kwargs=kw)
    run_eval("AudioGoal", "random", 1, seed=3, csv_path=tmp_path / "b.csv", env_kwargs=kw)
    run_eval("AudioGoal", "random", 1, seed=4, csv_path=tmp_path / "c.csv", env_kwargs=kw)
    a, b, c = (list(csv.DictReader(open(tmp_path / f"{n}.csv"))) for n in "abc")
    assert a[0] == b[0]
    assert a[0]["episode_id"] != c[0]["episode_id"]
    # so `--first` starts a part of a run, and `--jobs` plays its episodes in processes, with the rows of one run
    run_eval("AudioGoal", "random", 4, seed=3, csv_path=tmp_path / "d.csv", env_kwargs=kw)
    one = run_eval("AudioGoal", "random", 1, seed=3, csv_path=tmp_path / "e.csv", env_kwargs=kw, first=1)
    seen = []
    two = run_eval("AudioGoal", "random", 4, seed=3, csv_path=tmp_path / "f.csv", env_kwargs=kw, jobs=2,
                   progress=lambda i, row: seen.append(i))
    d, e, f = (list(csv.DictReader(open(tmp_path / f"{n}.csv"))) for n in "def")
    assert d[:2] == a and e == d[1:2] and one["first"] == 1
    assert f == d and sorted(seen) == [0, 1, 2, 3] and two["episodes"] == 4


def test_a_rerun_never_replaces_a_csv_whose_rows_it_would_lose(tmp_path):
    """Without --resume, a run over an existing CSV replaces it only when it repeats the same evaluation over the
    same episodes; an interrupted run's rows, another evaluation's, other episodes' or a stranger's file are
    refused (the file untouched) unless --overwrite."""
    from app.tasks.evaluate import run_eval
    from sonicverse_core.errors import ConfigError

    kw, a = {"max_steps": 20}, tmp_path / "a.csv"
    run_eval("AudioGoal", "random", 2, seed=3, csv_path=a, env_kwargs=kw)
    first = a.read_bytes()
    run_eval("AudioGoal", "random", 2, seed=3, csv_path=a, env_kwargs=kw)  # the same run again: replaced, the same
    assert a.read_bytes() == first
    refused = [(3, "random", 3, kw, r"keeps 2 finished episodes of this evaluation, of the 3 asked for: add "
                                   r"--resume to play the other 1"),
               (1, "random", 3, kw, r"holds episode 1, outside the episodes asked for"),
               (2, "random", 4, kw, r"another evaluation \(its seed differs\)"),
               (2, "random", 3, {"max_steps": 21}, r"another evaluation \(its env differs\)"),
               (2, "oracle", 3, kw, r"another evaluation \(its agent differs\)")]
    for n, agent, seed, env, msg in refused:
        with pytest.raises(ConfigError, match=msg):
            run_eval("AudioGoal", agent, n, seed=seed, csv_path=a, env_kwargs=env)
        assert a.read_bytes() == first
    with pytest.raises(ConfigError, match="give one"):
        run_eval("AudioGoal", "random", 3, seed=3, csv_path=a, env_kwargs=kw, resume=True, overwrite=True)
    stranger = tmp_path / "notes.csv"
    stranger.write_text("episode,remark\n0,keep me\n")
    with pytest.raises(ConfigError, match="missing or unreadable.*--overwrite"):
        run_eval("AudioGoal", "random", 1, seed=3, csv_path=stranger, env_kwargs=kw)
    assert stranger.read_text() == "episode,remark\n0,keep me\n"
    (tmp_path / "notes.csv.json").write_text("[1]\n")  # JSON, but not an evaluation's identity
    for resume in (False, True):
        with pytest.raises(ConfigError, match="missing or unreadable"):
            run_eval("AudioGoal", "random", 1, seed=3, csv_path=stranger, env_kwargs=kw, resume=resume)
    assert stranger.read_text() == "episode,remark\n0,keep me\n"
    run_eval("AudioGoal", "random", 3, seed=3, csv_path=a, env_kwargs=kw, resume=True)  # plays the 3rd only
    grown = a.read_bytes()
    assert grown.startswith(first) and len(grown.splitlines()) == 4
    run_eval("AudioGoal", "random", 2, seed=4, csv_path=a, env_kwargs=kw, overwrite=True)
    assert len(a.read_bytes().splitlines()) == 3 and a.read_bytes() != first


def test_a_stopped_evaluation_keeps_its_episodes_and_resumes(tmp_path):
    """The CSV is rewritten after every episode: SIGTERM in the middle of a run ends it with one line that says
    how many episodes the CSV keeps and how to go on; `--resume` (here with `--jobs 2`) plays the rest, and the CSV
    is the uninterrupted run's, byte for byte. A CSV of another evaluation, or a broken one, is refused."""
    from conftest import ROOT, run_cli

    base = ["eval", "--task", "AudioGoal", "--agent", "random", "--episodes", "6", "--seed", "5", "--max-steps",
            "100"]
    whole, part = tmp_path / "whole.csv", tmp_path / "part.csv"
    run_cli(*base, "--csv", str(whole), "--json", check_rc=0)
    exe = [sys.executable, "-m", "app.cli", *base, "--csv", str(part)]
    proc = subprocess.Popen(exe, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    head = []
    for line in proc.stderr:  # an episode's line comes once its row is in the CSV
        head.append(line)
        if line.startswith("episode "):
            break
    assert head and head[-1].startswith("episode "), "".join(head)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    err = "".join(head) + err
    kept = len(part.read_text().splitlines()) - 1
    last = err.strip().splitlines()[-1]  # (the lines before: an episode each, as a log shows them)
    assert proc.returncode == 2 and last.startswith("sonicverse: error: terminated (SIGTERM)"), err
    assert 1 <= kept < 6 and f"keeps its {kept} finished episode" in last and "--resume" in last
    before = part.read_bytes()
    r = run_cli(*base, "--csv", str(part))  # the same command again, without --resume: refused, nothing lost
    assert r.returncode == 2 and f"keeps {kept} finished episode" in r.stderr and "--resume" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and part.read_bytes() == before
    r = run_cli(*base, "--csv", str(part), "--resume", "--jobs", "2", "--json", check_rc=0)
    assert part.read_bytes() == whole.read_bytes() and json.loads(r.stdout)["episodes"] == 6
    r = run_cli(*base[:-4], "--seed", "6", "--max-steps", "100", "--csv", str(part), "--resume")
    assert r.returncode == 2 and "its seed differs" in r.stderr and part.read_bytes() == whole.read_bytes()
    part.write_text(whole.read_text() + "7,test/1,,\n")  # edited by hand: refused, one line
    r = run_cli(*base, "--csv", str(part), "--resume")
    assert r.returncode == 2 and "line 8 has fewer cells" in r.stderr and len(r.stderr.strip().splitlines()) == 1


STOP_IN_AN_EPISODE = {
    # a SIGTERM's raise that lands in code that catches every Exception (a damaged cache's fallback, a library): the
    # episode loop checks for a noted stop every step
    "swallowed": "            try:\n                errors.stop('terminated (SIGTERM)')\n"
                 "            except Exception:\n                pass  # swallowed, as a broad except would\n",
    # a SIGTERM that lands while a class body binds its fields (a module imported mid-episode) reaches the loop as a
    # RuntimeError (Python 3.11): it is still the stop
    "wrapped": "            type('Late', (), {'extra': Field()})\n",
}


@pytest.mark.parametrize("how", sorted(STOP_IN_AN_EPISODE))
def test_a_stop_in_an_episode_ends_the_evaluation_keeping_the_finished_episodes(tmp_path, monkeypatch, how):
    """A stop in the second episode, swallowed or wrapped on its way to the episode loop, still ends the run with
    the stop's own message, and the CSV keeps the episode that finished."""
    from app.tasks.evaluate import run_eval
    from sonicverse_core import errors

    (tmp_path / f"{how}_policy.py").write_text(
        "import numpy as np\n\nfrom sonicverse_core import errors\n\nEPISODES = []\n\n\nclass Field:\n"
        "    def __set_name__(self, owner, name):\n        errors.stop('terminated (SIGTERM)')\n\n\n"
        "class Policy:\n    def __init__(self, rng):\n        self.t = 0\n\n"
        "    def reset(self, env, obs, info):\n        EPISODES.append(0)\n        self.t = 0\n\n"
        "    def act(self, obs, info):\n        self.t += 1\n"
        "        if len(EPISODES) == 2 and self.t == 3:\n" + STOP_IN_AN_EPISODE[how] +
        "        return np.array([0.5, 0.0], np.float32)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    out = tmp_path / "x.csv"
    try:
        with pytest.raises(errors.Interrupted, match="^terminated .SIGTERM.; .* keeps its 1 finished episode"):
            run_eval("AudioGoal", f"{how}_policy:Policy", 3, seed=0, csv_path=out, env_kwargs={"max_steps": 10})
    finally:
        errors._STOPPED.clear()  # this process goes on: forget the stop noted for the test
    assert len(out.read_text().splitlines()) == 2


def test_a_failing_evaluation_job_stops_the_run_with_its_own_error(tmp_path, cli, monkeypatch):
    """An agent's bad action in one of `--jobs` processes reaches the user as that error, one line, exit 2; no
    episode finished, so no CSV is written."""
    (tmp_path / "nan_policy.py").write_text(
        "import numpy as np\n\n\nclass Policy:\n    def __init__(self, rng):\n        pass\n\n"
        "    def reset(self, env, obs, info):\n        pass\n\n"
        "    def act(self, obs, info):\n        return np.full(2, np.nan, np.float32)\n")
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    out = tmp_path / "x.csv"
    r = cli("eval", "--task", "AudioGoal", "--agent", "nan_policy:Policy", "--episodes", "2", "--jobs", "2",
            "--max-steps", "5", "--csv", str(out))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "finite" in r.stderr and not out.exists()
    import os

    cores = len(os.sched_getaffinity(0))
    for bad in (("--first", "-1"), ("--jobs", "0"), ("--jobs", str(cores + 1))):
        r = cli("eval", "--task", "AudioGoal", "--agent", "random", *bad)
        assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    r = cli("task", "run", "orientation-training", "--first", "2")
    assert r.returncode == 2 and "--first is for robot tasks" in r.stderr
