"""The hostile-user sweep: bad invocations of every command end in one line `sonicverse: error: ...` and exit code 2,
never a traceback, and before any long work (output paths and formats are checked when the line is parsed)."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from app.cli import main

AV_NAV = str(Path(__file__).resolve().parents[1] / "agents" / "checkpoints" / "av-nav_AudioGoal.pt")


@pytest.fixture(scope="module")
def bad(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad")
    (d / "folder.wav").mkdir()
    (d / "notes.txt").write_text("hello")
    (d / "noise.wav").write_bytes(b"RIFF\x00\x00\x00\x00WAVEjunk")
    (d / "corrupt.npz").write_bytes(b"PK\x03\x04 not a zip at all")
    np.savez(d / "other.npz", x=np.arange(3))
    (d / "trunc.svrec").write_bytes(b"SVREC1\n{\"scene\": ")
    (d / "empty.svrec").write_bytes(b"")
    (d / "take1.wav").write_bytes(b"an earlier person's take")
    return d


def table(d):
    out = str(d / "ok.wav")
    r = ["render", "shoebox:6x4x3", "--sound", "sofa", "--source", "1,1,1", "--listener", "3,2,1.5"]
    return [
        # argparse itself: unknown command, option, missing value, wrong choice
        [], ["frobnicate"], ["scene"], ["scene", "info"], ["scene", "info", "shoebox:6x4x3", "--nope"],
        ["eval", "--task", "Nope", "--agent", "oracle"],
        ["bake", "shoebox:6x4x3", "--per-room", "--whole-space"],  # the two late models at once
        # the task commands
        ["task"], ["task", "run", "nonexist"], ["task", "run", "speaker-following", "--episodes", "0"],
        ["task", "run", "orientation-training", "--noise", "nan"],
        ["task", "run", "orientation-training", "--agent", "oracle"],
        ["task", "run", "speaker-following", "--agent", "gan"],
        ["task", "run", "speaker-following", "--out", str(d / "notes.txt")],
        ["task", "run", "orientation-training", "--front-back", "2"],
        ["task", "run", "speaker-following", "--resume", "--overwrite", "--out", str(d / "sf")],
        ["task", "run", "orientation-training", "--first", "3"],
        ["task", "run", "orientation-training", "--overwrite"],  # nothing to replace: no --out
        ["task", "run", "speaker-following", "--overwrite"],
        ["eval", "--task", "AudioGoal", "--agent", "random", "--resume", "--overwrite", "--csv", str(d / "e.csv")],
        # a checkpoint of another task: it would run with the same sensors and score as if meant for this one
        ["task", "run", "speaker-following", "--agent", "av-nav", "--checkpoint", AV_NAV],
        ["train", "--recipe", "ppo", "--init", AV_NAV, "--task", "SemanticAudioNav",
         "--out", str(d / "ppo")],
        ["train", "--recipe", "ppo", "--resume", "--out", str(d / "ppo_resume")],
        ["train", "--homes", "0", "--out", str(d / "h0")], ["train", "--homes", "5001", "--out", str(d / "h1")],
        ["train", "--agent", "sound-localizer", "--homes", "40", "--out", str(d / "h2")],
        # numbers
        [*r, "--out", out, "--seconds", "nan"], [*r, "--out", out, "--seconds", "-1"],
        # positions outside the scene's bounds (the home has no outdoors), a floor plan no grid fits
        [*r[:4], "--source", "100,100,1", "--listener", "3,2,1.5", "--out", out],
        [*r[:6], "--listener", "3,2,-1.5,90", "--out", out],
        ["render", "shoebox:3000x3000x3", *r[2:], "--out", out],
        [*r, "--out", out, "--seconds", "inf"], [*r, "--out", out, "--sample-rate", "7"],
        [*r, "--out", out, "--block", "0"], [*r, "--out", out, "--rays", "-5"],
        ["bake", "shoebox:6x4x3", "--probes", "-3"], ["bake", "shoebox:6x4x3", "--seed", "-1"],
        ["bake", "shoebox:6x4x3", "--at", "1,2"], ["bake", "shoebox:6x4x3", "--at", "1,nan,1"],
        ["bake", "shoebox:6x4x3", "--at", "1,1,1", "--at", "100,100,1"],
        ["bench", "env", "--steps", "0"], ["bench", "env", "--workers", "-1"], ["bench", "env", "--size", "x"],
        ["bench", "audio", "--sources", "0"], ["bench", "audio", "--seconds", "nan"],
        ["bench", "rays", "--rays", "0"], ["bench", "accuracy", "--reference-rays", "10"],
        ["bench", "fidelity", "--rays", "5"], ["bench", "fidelity", "--realisations", "0"],
        ["bench", "fidelity", "--case", "attic"], ["bench", "fidelity", "--neighbour-tails", "5"],
        ["bench", "fidelity", "--min-scattering", "2"], ["bench", "fidelity", "--min-scattering", "nan"],
        ["bench", "fidelity", "--case", "sealed", "--min-scattering", "1"],
        ["bench", "audio", "--listener-room", "attic"], ["bench", "audio", "--neighbour-tails", "-1"],
        ["scene", "info", "builtin:three-rooms?door=ajar"], ["scene", "info", "builtin:three-rooms?middle=Cheese"],
        ["scene", "info", "builtin:three-rooms?hall=Carpet"],
        ["bench", "recogniser", "--commands", "0"], ["bench", "recogniser", "--homes", "x"],
        ["task", "train-recogniser", "--epochs", "0"], ["task", "train-recogniser", "--out", str(d / "w.txt")],
        ["bench", "vr", "--sizes", "512"], ["bench", "vr", "--frames", "2"], ["bench", "vr", "--audio-seconds", "-1"],
        ["eval", "--task", "AudioGoal", "--agent", "oracle", "--episodes", "0"],
        ["eval", "--task", "AudioGoal", "--agent", "oracle", "--seed", "-1"],
        ["eval", "--task", "AudioGoal", "--agent", "oracle", "--max-steps", "0"],
        ["vr", "--frames", "0"], ["vr", "--rate", "nan"], ["vr", "--size", "10x10"], ["vr", "--seed", "-1"],
        ["audio", "loopback-test", "--seconds", "nan"], ["audio", "live", "--sources", "-1"],
        ["demo", "--seconds", "0"],
        # positions
        [*r[:5], "--source", "1,1", "--listener", "3,2,1.5", "--out", out],
        [*r[:5], "--source", "1,1,1", "--listener", "3,2,x", "--out", out],
        # output paths: a folder, a missing or unwritable place, an unsupported format
        [*r, "--out", str(d / "folder.wav")], [*r, "--out", str(d / "x.mp3")], [*r, "--out", str(d)],
        [*r, "--out", str(d / "notes.txt" / "a.wav")],
        ["scene", "map", "shoebox:6x4x3", "--out", str(d / "map.jpg")],
        ["scene", "map", "shoebox:6x4x3", "--out", str(d / "notes.txt" / "m.png")],
        ["bench", "accuracy", "--plot", str(d / "p.svg")], ["bench", "fidelity", "--plot", str(d / "f.svg")], ["demo", "--out", str(d / "notes.txt")],
        ["vr", "--out", str(d / "notes.txt")], ["vr", "--record", str(d / "r.txt")],
        ["eval", "--task", "AudioGoal", "--agent", "oracle", "--csv", str(d / "folder.wav")],
        ["audio", "live", "--record", str(d / "rec.flac")],
        ["audio", "live", "--record", str(d / "take1.wav")],  # an earlier take: refused before any device opens
        # inputs: missing, not a file, corrupt
        ["vr", "--backend", "headless", "--replay", str(d / "missing.npz")],
        ["vr", "--backend", "headless", "--replay", str(d / "notes.txt")],
        ["vr", "--backend", "headless", "--replay", str(d / "corrupt.npz")],
        ["vr", "--backend", "headless", "--replay", str(d / "other.npz")],
        ["vr", "--backend", "headless", "--replay", str(d / "trunc.svrec")],
        ["vr", "--backend", "headless", "--replay", str(d / "empty.svrec")],
        [*r[:3], "--sound", str(d / "noise.wav"), *r[5:], "--out", out],
        [*r[:3], "--sound", str(d / "missing.wav"), *r[5:], "--out", out],
        [*r[:3], "--sound", "sofa/99", *r[5:], "--out", out],
        # scenes
        ["scene", "info", "shoebox:0.3x0.3x0.3x"], ["scene", "info", "shoebox:-1x2x3"],
        ["scene", "info", "shoebox:nanx2x3"], ["scene", "info", str(d / "notes.txt")],
        ["vr", "--backend", "headless", "--scene", "shoebox:0.3x0.3x0.3", "--frames", "3", "--out", str(d / "vr")],
    ]


def test_every_bad_invocation_is_one_line_and_exit_2(bad, capsys):
    failures = []
    for argv in table(bad):
        code = main(argv)
        cap = capsys.readouterr()
        lines = cap.err.strip().splitlines()
        if code != 2 or len(lines) != 1 or not lines[0].startswith("sonicverse: error:") or "Traceback" in cap.err:
            failures.append((argv, code, cap.err[-400:]))
    assert not failures, "\n".join(f"{a} -> {c}: {e}" for a, c, e in failures)


def test_a_bad_scheduling_setting_is_one_line_before_any_audio_starts(monkeypatch, capsys):
    """SONICVERSE_RT_NICE naming a thread the pipeline has not: refused before the JACK server or the stream starts
    (in the callback it would be an error a block)."""
    monkeypatch.setenv("SONICVERSE_RT_NICE", "callback,bogus")
    assert main(["bench", "vr", "--task", "speaker-following", "--agent", "scripted", "--audio-seconds", "2"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == "sonicverse: error: SONICVERSE_RT_NICE: unknown thread role(s) ['bogus']; known: " \
        "callback, supervisor, robots, server, or none", err


def test_nothing_is_written_when_the_output_is_refused(bad, capsys):
    assert main(["render", "shoebox:6x4x3", "--sound", "sofa", "--source", "1,1,1", "--listener", "3,2,1.5",
                 "--out", str(bad / "out.mp3")]) == 2
    assert not (bad / "out.mp3").exists()
    assert main(["audio", "live", "--record", str(bad / "take1.wav")]) == 2
    assert (bad / "take1.wav").read_bytes() == b"an earlier person's take"


def test_a_refused_output_names_the_file_asked_for(capsys):
    """A place where no file can be made (here /proc) is reported with the path the user gave, not the temporary
    file the atomic write would have renamed."""
    assert main(["render", "shoebox:6x4x3", "--sound", "sofa", "--source", "1,1,1", "--listener", "3,2,1.5",
                 "--seconds", "0.1", "--out", "/proc/out.wav"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("sonicverse: error:") and err.endswith(": /proc/out.wav") and ".tmp" not in err, err


def _command_that_runs(func, monkeypatch):
    import argparse

    import app.cli as cli

    parser = argparse.ArgumentParser()
    parser.set_defaults(func=func, verbose=0)
    monkeypatch.setattr(cli, "build_parser", lambda: parser)


def test_a_stop_that_python_wrapped_is_still_one_line_and_exit_2(wrapped_stop, monkeypatch, capsys):
    """CI saw SIGTERM land while a task module was imported: Python wrapped the handler's raise in a RuntimeError
    and the command died with a traceback and exit 1."""
    _command_that_runs(lambda args: wrapped_stop(), monkeypatch)
    assert main([]) == 2
    assert capsys.readouterr().err == "sonicverse: error: terminated (SIGTERM)\n"


def test_ctrl_c_that_python_wrapped_is_still_one_line_and_exit_2(wrapped_stop, monkeypatch, capsys):
    def ctrl_c():
        raise KeyboardInterrupt

    _command_that_runs(lambda args: wrapped_stop(ctrl_c), monkeypatch)
    assert main([]) == 2
    assert capsys.readouterr().err == "sonicverse: error: interrupted\n"


def test_an_error_of_our_own_is_not_taken_for_a_stop(monkeypatch):
    def command(args):
        raise RuntimeError("a bug")

    _command_that_runs(command, monkeypatch)
    with pytest.raises(RuntimeError, match="a bug"):  # no stop was noted: a bug stays a traceback, not a stop
        main([])


def test_help_and_version_exit_0(capsys):
    assert main(["--version"]) == 0 and capsys.readouterr().out.startswith("sonicverse ")
    assert main(["render", "--help"]) == 0 and "--seconds" in capsys.readouterr().out


def test_every_option_has_help():
    """No option of any command is left without a help text."""
    import argparse

    from app.cli import build_parser

    missing = []

    def walk(p, path):
        for act in p._actions:
            if isinstance(act, argparse._SubParsersAction):
                for name, sp in act.choices.items():
                    walk(sp, path + [name])
            elif act.option_strings and act.help in (None, "") and act.dest != "help":
                missing.append(" ".join(path + [act.option_strings[-1]]))

    walk(build_parser(), ["sonicverse"])
    assert not missing, missing


def test_a_closed_pipe_is_not_an_error():
    """`sonicverse ... --json | head -c 10`: the reader goes away; no traceback, exit 0."""
    p = subprocess.run(f"'{sys.executable}' -m app.cli scene info builtin:apartment --json | head -c 10",
                       shell=True, capture_output=True, text=True, timeout=300)
    assert "Traceback" not in p.stderr and "Exception" not in p.stderr, p.stderr


def test_a_crash_in_a_c_library_says_where_it_happened():
    """A command that dies of a signal in native code (`bench camera` died of SIGSEGV once in `make test`, with
    nothing on stderr) prints Python's fault report: the signal and the stack of the command that was running; so
    does a Python process it starts (PYTHONFAULTHANDLER)."""
    script = ("import ctypes, sys\n"
              "import app.cli as cli\n"
              "import argparse\n"
              "import subprocess\n"
              "def crash_in_native_code(args):\n"
              "    subprocess.run([sys.executable, '-c', 'import ctypes; ctypes.string_at(0)'])  # a worker's crash\n"
              "    ctypes.string_at(0)\n"
              "p = argparse.ArgumentParser()\n"
              "p.set_defaults(func=crash_in_native_code, verbose=0)\n"
              "cli.build_parser = lambda: p\n"
              "sys.argv = ['sonicverse']\n"
              "sys.exit(cli.main())\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONFAULTHANDLER"}  # none but the CLI's own
    r = subprocess.run([sys.executable, "-c", script], cwd=Path(__file__).resolve().parents[1], capture_output=True,
                       text=True, timeout=120, env=env)
    assert r.returncode == -11, (r.returncode, r.stderr)
    assert "Fatal Python error: Segmentation fault" in r.stderr and "crash_in_native_code" in r.stderr
    assert r.stderr.count("Fatal Python error: Segmentation fault") == 2  # the worker it started reports its own
