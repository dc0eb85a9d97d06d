"""The launcher window driven as an operator would (Qt offscreen): create a participant, start a headless session
with the simulated participant, pause, abort, resume, skip, notes; what it did is in the database exactly once."""
import json

import pytest

from PyQt6 import QtCore, QtWidgets  # noqa: E402  (a missing PyQt6 fails here: it is a main dependency)
from PyQt6.QtTest import QSignalSpy, QTest  # noqa: E402

STUDY = """
name = "window"
seed = 5
[conditions.a]
hrtf = "on"
[conditions.b]
hrtf = "off"
[[blocks]]
name = "follow"
task = "speaker-following"
trials = 2
agent = "scripted"
time_limit_s = 10
[[blocks]]
name = "turns"
task = "orientation-training"
trials = 2
"""


@pytest.fixture
def app():
    return QtWidgets.QApplication.instance() or QtWidgets.QApplication(["test"])


def _wait_for(win, spy, kind: str, timeout_ms: int = 300_000) -> dict:
    """Until the window's study signal says ``kind`` (event-driven: QSignalSpy.wait runs the event loop)."""
    seen = 0
    while True:
        while seen < len(spy):
            k, p = spy[seen]
            seen += 1
            if k == kind:
                return p
        assert spy.wait(timeout_ms), f"no '{kind}' event"


def test_operator_session_pause_abort_resume(app, tmp_path):
    from app.study.window import LauncherWindow

    f = tmp_path / "study.toml"
    f.write_text(STUDY)
    win = LauncherWindow(tmp_path / "data", str(f))
    win.show()
    win.activateWindow()
    assert QTest.qWaitForWindowActive(win, 10_000)  # keyboard shortcuts go to the active window
    assert not win.start_btn.isEnabled()  # nobody picked yet
    QTest.keyClicks(win.new_id, "W1")
    QTest.keyClicks(win.identity, "Grace H.")
    QTest.mouseClick(win.add_btn, QtCore.Qt.MouseButton.LeftButton)
    assert win.current_participant() == "W1" and "->" in win.order.text()
    win.new_id.setText("W1")
    QTest.mouseClick(win.add_btn, QtCore.Qt.MouseButton.LeftButton)
    assert "exists" in win.status.text()  # a repeated id is refused, nothing overwritten
    assert [p["id"] for p in win.store.participants()] == ["W1"]

    spy = QSignalSpy(win.studyEvent)
    QTest.keyClick(win, QtCore.Qt.Key.Key_R, QtCore.Qt.KeyboardModifier.ControlModifier)  # start
    assert win.session == 1 and not win.start_btn.isEnabled() and win.pause_btn.isEnabled()
    QTest.keyClick(win, QtCore.Qt.Key.Key_P, QtCore.Qt.KeyboardModifier.ControlModifier)  # pause after this trial
    paused = _wait_for(win, spy, "paused")
    done_at_pause = win.store.finished_slots("W1", 1)
    assert paused["slot"] == len(done_at_pause) < 8  # stopped at a trial boundary, before the end
    assert win.table.rowCount() == len(done_at_pause)
    QTest.mouseClick(win.abort_btn, QtCore.Qt.MouseButton.LeftButton)
    ended = _wait_for(win, spy, "ended")
    assert ended["status"] == "aborted" and "resume" in ended["reason"]
    assert win.store.finished_slots("W1", 1) == done_at_pause  # nothing ran after the pause
    assert win.store.unfinished("W1")["session"] == 1
    assert win.resume_btn.isEnabled() and not win.start_btn.isEnabled()

    win.note.setPlainText("participant asked for water")
    QTest.mouseClick(win.note_btn, QtCore.Qt.MouseButton.LeftButton)

    spy2 = QSignalSpy(win.studyEvent)
    QTest.mouseClick(win.resume_btn, QtCore.Qt.MouseButton.LeftButton)
    QTest.mouseClick(win.skip_btn, QtCore.Qt.MouseButton.LeftButton)  # skip the trial running (or the next)
    ended = _wait_for(win, spy2, "ended")
    assert ended["status"] == "finished", ended
    st = win.store
    rows = st.trials("W1", 1, status=None)
    assert [r["slot"] for r in rows] == list(range(8))  # every slot exactly once, in order
    assert sum(r["status"] == "skipped" for r in rows) == 1
    assert win.table.rowCount() == 8 and win.progress.value() == 8
    kinds = [e["kind"] for e in st.events("W1", 1)]
    assert "paused" in kinds and "resume" in kinds and "note" in kinds
    assert st.session("W1", 1)["status"] == "finished"
    order = json.loads(st.session("W1", 1)["order_json"])
    assert [r["condition"] for r in rows[:2]] == [order[0]] * 2  # the frozen order was kept through the resume
    assert win.start_btn.isEnabled()  # the next session may start
    win.close()


AUDIO_CHECK = """
import json, sys
from PyQt6 import QtWidgets
app = QtWidgets.QApplication([])
from app.study.window import LauncherWindow
win = LauncherWindow(sys.argv[1], "default")
out = {"outputs": [win.out_dev.itemText(i) for i in range(win.out_dev.count())],
       "inputs": [win.in_dev.itemText(i) for i in range(win.in_dev.count())]}
win.test_tone()
out["tone"] = win.status.text()
win.mic_btn.setChecked(True)
out["mic_open"] = win._mic is not None
out["blocks"] = win.mic_heard.wait(20)
win._tick()
out["meter"] = win.meter.value()
win.mic_btn.setChecked(False)
out["mic_closed"] = win._mic is None
win.close()
print(json.dumps(out))
"""


def test_audio_checks_on_jack(tmp_path, jack):
    """The set-up panel's audio checks on JACK's dummy backend (in a process of its own: PortAudio is initialised
    there while the server runs): its devices are listed, the test tone plays, the microphone meter's stream
    delivers blocks and reads silence as an empty meter, and closes."""
    import subprocess
    import sys
    from pathlib import Path

    r = subprocess.run([sys.executable, "-c", AUDIO_CHECK, str(tmp_path / "d")], capture_output=True, text=True,
                       timeout=120, cwd=Path(__file__).resolve().parents[1])
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert any("JACK" in d or "system" in d for d in out["outputs"][1:]), out
    assert len(out["inputs"]) > 1
    assert "440 Hz" in out["tone"], out
    assert out["mic_open"] and out["blocks"] and out["mic_closed"]
    assert out["meter"] == 0  # the dummy backend captures silence
