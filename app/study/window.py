"""The launcher window (PyQt6): participants, the study, the session's frozen condition order, backend and audio
devices (a test tone and a live microphone level meter), start / resume / pause / skip / abort with keyboard
shortcuts, progress (block, trial, time), each trial's quality figures (missed frames, xruns, audio latency) and
operator notes. Everything it does is also a ``sonicverse study`` command.

Headless sessions (the simulated participant) run in a worker thread, so the window stays live; desktop and headset
sessions run in the window's own thread, whose VR loop keeps handling the window's events (Qt widgets live in one
thread). Pause takes effect when the running trial ends; skip and abort end the running trial at its next step.

Shortcuts: Ctrl+R start, Ctrl+E resume, Ctrl+P pause / continue, Ctrl+K skip, Ctrl+Shift+A abort, Ctrl+N add the
note.
"""
from __future__ import annotations

import json
import threading
import time

import numpy as np

from sonicverse_core.errors import DependencyError, SonicverseError

try:
    from PyQt6 import QtCore, QtGui, QtWidgets
except ImportError as exc:  # pragma: no cover - PyQt6 is a main dependency
    raise DependencyError(f"the study launcher needs PyQt6 (pip install -r requirements.txt): {exc}") from None

BACKENDS = (("headless (simulated participant)", "headless"), ("desktop", "desktop"), ("headset (OpenVR)", "openvr"))
HEADLINE = {"orientation-training": ("azimuth_error_deg", "azimuth error {:.1f} deg"),
            "speaker-following": ("time_in_band", "in band {:.2f}"), "voice-retrieval": ("success", "success {:.0f}")}


class _Worker(QtCore.QThread):
    """Runs a StudyRunner; the runner's events arrive in the window as a queued signal."""

    event = QtCore.pyqtSignal(str, dict)

    def __init__(self, make_runner):
        super().__init__()
        self.make_runner = make_runner

    def run(self) -> None:
        try:
            self.make_runner(lambda kind, p: self.event.emit(kind, _safe(p))).run()
        except SonicverseError as exc:
            self.event.emit("ended", {"status": "aborted", "reason": str(exc)})
            return
        except Exception as exc:  # noqa: BLE001 - shown to the operator, the session stays resumable
            self.event.emit("ended", {"status": "error", "reason": f"{type(exc).__name__}: {exc}"})
            return
        self.event.emit("ended", {"status": "finished"})


def _safe(p: dict) -> dict:
    return json.loads(json.dumps(p, default=str))


class LauncherWindow(QtWidgets.QMainWindow):
    studyEvent = QtCore.pyqtSignal(str, dict)  # every runner event, then ("ended", {"status": ...})

    def __init__(self, data_dir="study-data", study="default"):
        super().__init__()
        from app.study.runner import Controls
        from app.study.spec import load_study
        from app.study.store import StudyStore

        self.store = StudyStore(data_dir)
        self.study = load_study(study)
        self.controls = Controls()
        self.worker: _Worker | None = None
        self.session: int | None = None
        self.t0 = None
        self._mic = None
        self._level = 0.0
        self.mic_blocks = 0  # blocks the level meter's stream has delivered
        self.mic_heard = threading.Event()  # set once it has delivered some
        self.setWindowTitle(f"Sonicverse study launcher: {self.study.name}")
        self._build()
        self._refresh_participants()
        self._set_running(False)

    # --- layout -----------------------------------------------------------------------------------------------
    def _build(self) -> None:
        W = QtWidgets
        root = W.QWidget()
        self.setCentralWidget(root)
        grid = W.QHBoxLayout(root)
        left, right = W.QVBoxLayout(), W.QVBoxLayout()
        grid.addLayout(left, 1)
        grid.addLayout(right, 2)

        box = W.QGroupBox("Participants")
        v = W.QVBoxLayout(box)
        self.participants = W.QListWidget()
        self.participants.currentTextChanged.connect(self._on_participant)
        v.addWidget(self.participants)
        self.new_id = W.QLineEdit(placeholderText="new pseudonymous id (e.g. P007)")
        self.identity = W.QLineEdit(placeholderText="identifying details (optional, kept apart)")
        self.add_btn = W.QPushButton("Add participant")
        self.add_btn.clicked.connect(self.add_participant)
        for w in (self.new_id, self.identity, self.add_btn):
            v.addWidget(w)
        left.addWidget(box)

        box = W.QGroupBox("Study")
        f = W.QFormLayout(box)
        s = self.study
        f.addRow("study", W.QLabel(f"{s.name} ({s.sha256[:12]})"))
        f.addRow("conditions", W.QLabel(", ".join(
            f"{c.name} (HRTF {'on' if c.hrtf else 'off'}, reverb {'on' if c.reverb else 'off'})"
            for c in s.conditions)))
        f.addRow("blocks", W.QLabel(", ".join(
            f"{b.name}: {b.task} x{b.trials}" + (f" +{b.practice} practice" if b.practice else "")
            + (" per condition" if b.per_condition else f" ({b.condition})") for b in s.blocks)))
        self.order = W.QLabel("-")
        f.addRow("condition order", self.order)
        left.addWidget(box)

        box = W.QGroupBox("Set-up")
        f = W.QFormLayout(box)
        self.backend = W.QComboBox()
        for label, _ in BACKENDS:
            self.backend.addItem(label)
        f.addRow("backend", self.backend)
        self.out_dev, self.in_dev = W.QComboBox(), W.QComboBox()
        self._fill_devices()
        f.addRow("audio output", self.out_dev)
        f.addRow("microphone", self.in_dev)
        row = W.QHBoxLayout()
        self.tone_btn = W.QPushButton("Test tone")
        self.tone_btn.clicked.connect(self.test_tone)
        self.mic_btn = W.QPushButton("Listen", checkable=True)
        self.mic_btn.toggled.connect(self.listen)
        self.meter = W.QProgressBar(maximum=100, textVisible=False)
        for w in (self.tone_btn, self.mic_btn, self.meter):
            row.addWidget(w)
        f.addRow("check", row)
        left.addWidget(box)

        row = W.QHBoxLayout()
        self.start_btn = W.QPushButton("Start (Ctrl+R)")
        self.resume_btn = W.QPushButton("Resume (Ctrl+E)")
        self.pause_btn = W.QPushButton("Pause (Ctrl+P)")
        self.skip_btn = W.QPushButton("Skip trial (Ctrl+K)")
        self.abort_btn = W.QPushButton("Abort (Ctrl+Shift+A)")
        for b, slot, key in ((self.start_btn, self.start, "Ctrl+R"), (self.resume_btn, self.resume, "Ctrl+E"),
                             (self.pause_btn, self.toggle_pause, "Ctrl+P"), (self.skip_btn, self.skip, "Ctrl+K"),
                             (self.abort_btn, self.abort, "Ctrl+Shift+A")):
            b.clicked.connect(slot)
            QtGui.QShortcut(QtGui.QKeySequence(key), self, activated=b.click,
                            context=QtCore.Qt.ShortcutContext.ApplicationShortcut)
            row.addWidget(b)
        right.addLayout(row)
        self.progress = W.QProgressBar()
        self.where = W.QLabel("no session running")
        self.status = W.QLabel("ready")
        for w in (self.progress, self.where, self.status):
            right.addWidget(w)
        self.table = W.QTableWidget(0, 9)
        self.table.setHorizontalHeaderLabels(["#", "block", "trial", "condition", "status", "result",
                                              "missed frames", "xruns", "latency ms"])
        self.table.horizontalHeader().setStretchLastSection(True)
        self.table.verticalHeader().setVisible(False)
        right.addWidget(self.table, 1)
        box = W.QGroupBox("Operator notes (saved with the session)")
        v = W.QHBoxLayout(box)
        self.note = W.QPlainTextEdit()
        self.note.setMaximumHeight(60)
        self.note_btn = W.QPushButton("Add note (Ctrl+N)")
        self.note_btn.clicked.connect(self.add_note)
        QtGui.QShortcut(QtGui.QKeySequence("Ctrl+N"), self, activated=self.note_btn.click,
                        context=QtCore.Qt.ShortcutContext.ApplicationShortcut)
        v.addWidget(self.note, 1)
        v.addWidget(self.note_btn)
        right.addWidget(box)
        self.clock = QtCore.QTimer(self, interval=200)
        self.clock.timeout.connect(self._tick)
        self.studyEvent.connect(self._on_event)
        self.resize(1100, 640)

    def _fill_devices(self) -> None:
        self.out_dev.addItem("system default", None)
        self.in_dev.addItem("system default", None)
        try:
            import sounddevice as sd

            for i, d in enumerate(sd.query_devices()):
                if d["max_output_channels"] >= 2:
                    self.out_dev.addItem(d["name"], i)
                if d["max_input_channels"] >= 1:
                    self.in_dev.addItem(d["name"], i)
        except Exception as exc:  # noqa: BLE001 - no PortAudio devices: say so, the headless backend needs none
            self.out_dev.setToolTip(f"no audio devices: {exc}")

    # --- participants -----------------------------------------------------------------------------------------
    def _refresh_participants(self, select: str | None = None) -> None:
        cur = select or self.current_participant()
        self.participants.clear()
        for p in self.store.participants():
            self.participants.addItem(p["id"])
        if cur:
            items = self.participants.findItems(cur, QtCore.Qt.MatchFlag.MatchExactly)
            if items:
                self.participants.setCurrentItem(items[0])

    def current_participant(self) -> str | None:
        it = self.participants.currentItem()
        return it.text() if it else None

    def add_participant(self) -> None:
        pid = self.new_id.text().strip()
        ident = self.identity.text().strip()
        try:
            self.store.add_participant(pid, {"details": ident} if ident else None)
        except SonicverseError as exc:
            self._say(str(exc), error=True)
            return
        self.new_id.clear()
        self.identity.clear()
        self._refresh_participants(select=pid)
        self._say(f"participant {pid} enrolled")

    def _on_participant(self, pid: str) -> None:
        if not pid:
            self.order.setText("-")
            return
        open_ = self.store.unfinished(pid)
        if open_ is not None:
            self.order.setText(f"{' -> '.join(json.loads(open_['order_json']))} (session {open_['session']}, "
                               f"unfinished: resume)")
        else:
            from app.study.design import assign_row, williams

            p = self.store.participant(pid)
            row = assign_row(self.study.counterbalance, len(self.study.conditions), p["enrol"], {})
            names = [self.study.conditions[i].name for i in williams(len(self.study.conditions))[row]]
            nxt = len(self.store.sessions(pid)) + 1
            extra = " (least-filled: fixed at start)" if self.study.counterbalance != "latin" else ""
            self.order.setText(f"{' -> '.join(names)} (next: session {nxt}){extra}")
        self._set_running(False)

    # --- audio checks -----------------------------------------------------------------------------------------
    def test_tone(self) -> None:
        try:
            import sounddevice as sd

            sr = 48_000
            t = np.arange(sr // 2) / sr
            tone = (0.2 * np.sin(2 * np.pi * 440 * t) * np.minimum(1, np.minimum(t, t[::-1]) / 0.01)).astype(
                np.float32)
            sd.play(np.stack([tone, tone], 1), sr, device=self.out_dev.currentData())
            self._say("test tone: 440 Hz, 0.5 s")
        except Exception as exc:  # noqa: BLE001 - a device problem is the operator's to fix
            self._say(f"test tone failed: {exc}", error=True)

    def listen(self, on: bool) -> None:
        if not on:
            if self._mic is not None:
                self._mic.stop()
                self._mic.close()
                self._mic = None
            self.meter.setValue(0)
            return
        try:
            import sounddevice as sd

            def cb(indata, frames, t, status):  # the PortAudio thread: two numbers written
                self._level = float(np.sqrt(np.mean(indata.astype(np.float64) ** 2)))
                self.mic_blocks += 1
                if self.mic_blocks >= 4:
                    self.mic_heard.set()

            self._mic = sd.InputStream(device=self.in_dev.currentData(), channels=1, callback=cb)
            self._mic.start()
            self.clock.start()
        except Exception as exc:  # noqa: BLE001
            self.mic_btn.setChecked(False)
            self._say(f"microphone failed: {exc}", error=True)

    # --- running ----------------------------------------------------------------------------------------------
    def backend_name(self) -> str:
        return BACKENDS[self.backend.currentIndex()][1]

    def start(self) -> None:
        from app.study.runner import start_session

        pid = self.current_participant()
        if not pid:
            self._say("pick or add a participant first", error=True)
            return
        b = self.backend_name()
        try:
            n = start_session(self.store, self.study, pid, b, b == "headless", self.out_dev.currentData())
        except SonicverseError as exc:
            self._say(str(exc), error=True)
            return
        self._launch(pid, n, b)

    def resume(self) -> None:
        pid = self.current_participant()
        s = self.store.unfinished(pid) if pid else None
        if s is None:
            self._say("no unfinished session for this participant", error=True)
            return
        self._launch(pid, s["session"], s["backend"])

    def _launch(self, pid: str, n: int, backend: str) -> None:
        from app.study.runner import Controls, StudyRunner
        from app.study.spec import load_study

        study = load_study(self.store.session_dir(pid, n) / "study.toml")
        self.controls = Controls()
        self.session, self.pid = n, pid
        self.table.setRowCount(0)
        for t in self.store.trials(pid, n, status=None):
            self._add_row(t)
        self.t0 = time.monotonic()
        self.clock.start()
        self._on_participant(pid)
        self._set_running(True)
        self._say(f"session {n} of {pid} running ({backend})")

        def make(emit):
            return StudyRunner(self.store, study, pid, n, backend, self.controls, emit, self.out_dev.currentData())

        if backend == "headless":
            self.worker = _Worker(make)
            self.worker.event.connect(self.studyEvent.emit)
            self.worker.start()
        else:  # the VR loop runs here and keeps the window's events going
            QtCore.QTimer.singleShot(0, lambda: self._run_here(make))

    def _run_here(self, make) -> None:
        try:
            make(lambda kind, p: self.studyEvent.emit(kind, _safe(p))).run()
        except SonicverseError as exc:
            self.studyEvent.emit("ended", {"status": "aborted", "reason": str(exc)})
            return
        self.studyEvent.emit("ended", {"status": "finished"})

    def toggle_pause(self) -> None:
        if self.controls.paused:
            self.controls.resume()
            self.pause_btn.setText("Pause (Ctrl+P)")
            self._say("continuing")
        else:
            self.controls.pause()
            self.pause_btn.setText("Continue (Ctrl+P)")
            self._say("pausing after this trial")

    def skip(self) -> None:
        self.controls.skip()
        self._say("skipping the running trial")

    def abort(self) -> None:
        self.controls.abort("aborted by the operator")
        self._say("aborting: the running trial is not kept")

    def add_note(self) -> None:
        text = self.note.toPlainText().strip()
        pid = self.current_participant()
        if not text or not pid:
            return
        self.store.event(pid, self.session, "note", text)
        self.note.clear()
        self._say("note saved")

    def _on_event(self, kind: str, p: dict) -> None:
        if kind == "trial_started":
            self.progress.setMaximum(p["total"])
            self.where.setText(f"block {p['block'] + 1} ({p['block_name']}, {p['condition']}), trial "
                               f"{p['trial'] + 1}{' (practice)' if p['practice'] else ''}")
        elif kind == "trial_done":
            self._add_row(p)
            self.progress.setValue(self.table.rowCount())
        elif kind == "paused":
            self._say("paused: press Continue (Ctrl+P)")
        elif kind == "break":
            self.pause_btn.setText("Continue (Ctrl+P)")
            self._say(f"break ({p['seconds']:g} s): press Continue when the participant is ready")
        elif kind == "finished" and p.get("quality_flags"):
            self._say("finished with quality warnings: " + "; ".join(p["quality_flags"][:3]), error=True)
        elif kind == "ended":
            self._set_running(False)
            self.clock.stop()
            self.pause_btn.setText("Pause (Ctrl+P)")
            if p["status"] == "finished":
                if not self.status.text().startswith("finished with"):
                    self._say("session finished")
            else:
                self._say(f"session stopped: {p.get('reason', '')}", error=p["status"] == "error")
            self._on_participant(self.current_participant() or "")

    def _add_row(self, t: dict) -> None:
        r = self.table.rowCount()
        self.table.insertRow(r)
        m, q = t.get("metrics") or {}, t.get("quality") or {}
        key, fmt = HEADLINE.get(t["task"], (None, ""))
        res = m.get(key)
        cells = [t["slot"] + 1, t["block"] + 1, t["trial"] + 1, t["condition"],
                 t["status"] + (" (practice)" if t.get("practice") else ""),
                 fmt.format(res) if isinstance(res, (int, float)) else "",
                 q.get("missed_frames"), q.get("xruns"), q.get("latency_ms")]
        for c, v in enumerate(cells):
            self.table.setItem(r, c, QtWidgets.QTableWidgetItem("-" if v is None else str(v)))
        self.table.resizeColumnsToContents()
        self.table.scrollToBottom()

    def _tick(self) -> None:
        if self.t0 is not None and self.worker is not None and self.worker.isRunning():
            el = time.monotonic() - self.t0
            self.progress.setFormat(f"%v / %m trials, {int(el // 60):02d}:{int(el % 60):02d}")
        if self._mic is not None:
            db = 20 * np.log10(max(self._level, 1e-6))
            self.meter.setValue(int(np.clip((db + 60) / 60 * 100, 0, 100)))

    def _set_running(self, running: bool) -> None:
        has = self.current_participant() is not None
        unfinished = has and self.store.unfinished(self.current_participant()) is not None
        self.start_btn.setEnabled(not running and has and not unfinished)
        self.resume_btn.setEnabled(not running and unfinished)
        for b in (self.pause_btn, self.skip_btn, self.abort_btn):
            b.setEnabled(running)
        for w in (self.participants, self.add_btn, self.backend):
            w.setEnabled(not running)

    def _say(self, text: str, error: bool = False) -> None:
        self.status.setText(text)
        self.status.setStyleSheet("color: #b00020" if error else "")

    def closeEvent(self, ev) -> None:  # noqa: N802 - Qt's name
        if self.worker is not None and self.worker.isRunning():
            self.controls.abort("the launcher window was closed")
            self.worker.wait()
        self.listen(False)
        super().closeEvent(ev)


def run_window(data_dir="study-data", study="default") -> int:
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(["sonicverse study"])
    w = LauncherWindow(data_dir, study)
    w.show()
    return int(app.exec())
