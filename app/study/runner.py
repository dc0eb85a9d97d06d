"""Runs a session: its frozen plan from the first unfinished trial, each trial committed when it ends.

The operator (the launcher window, or signals in a headless run) acts through :class:`Controls`: pause (after the
running trial), resume, skip (the running trial is recorded as skipped), abort (the running trial is recorded as
aborted in the events and the session stays unfinished, to be resumed). SIGINT and SIGTERM abort headless runs the
same way. A break between blocks is a pause that says so (headless runs with the simulated participant log it and
go on).
"""
from __future__ import annotations

import json
import signal
import threading
import time
from contextlib import contextmanager

from sonicverse_core.errors import Interrupted, StudyError, check_stopped, stop_behind, stop_held


class TrialSkipped(Exception):
    pass


class TrialAborted(Exception):
    pass


def _stop_reason(exc: BaseException) -> str | None:
    """Why ``exc`` stops the session (the operator's abort, Ctrl-C, SIGTERM, even when a library wrapped its raise
    on the way up), or None for an error of its own."""
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted (SIGINT)"
    if isinstance(exc, TrialAborted):
        return str(exc) or "aborted"
    stop = stop_behind(exc)
    return None if stop is None else str(stop) or "interrupted"


class Controls:
    """Requests from the operator, safe to make from any thread."""

    def __init__(self):
        self._go = threading.Event()
        self._go.set()
        self._skip = False
        self._abort: str | None = None

    @property
    def paused(self) -> bool:
        return not self._go.is_set()

    def pause(self) -> None:
        self._go.clear()

    def resume(self) -> None:
        self._go.set()

    def skip(self) -> None:
        self._skip = True

    def abort(self, reason: str = "aborted by the operator") -> None:
        self._abort = reason
        self._go.set()

    @property
    def abort_reason(self) -> str | None:
        return self._abort

    def check(self) -> None:
        """Between a trial's steps: raise to skip or abort it."""
        if self._abort:
            raise TrialAborted(self._abort)
        if self._skip:
            self._skip = False
            raise TrialSkipped()

    def wait(self) -> None:
        """Block while paused (until resume or abort)."""
        self._go.wait()


@contextmanager
def _signals_held():
    """Hold SIGINT and SIGTERM while a trial is being committed (main thread only): its row lands in the database
    and the CSV together, and the signal is handled right after."""
    main = threading.current_thread() is threading.main_thread()
    if main:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        with stop_held():  # SIGTERM handed to another thread still runs its handler here: it waits for the end
            yield
    finally:
        if main:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


def manifest(backend: str, simulated: bool, audio_device=None) -> dict:
    """What a session was run with: code version, packages, machine, backend, devices."""
    import platform
    import subprocess
    import sys
    from importlib import metadata
    from pathlib import Path

    pkgs = {}
    for name in ("sonicverse", "numpy", "scipy", "torch", "PyQt6", "sounddevice", "pyrender", "trimesh", "embreex",
                 "openvr", "numba"):
        try:
            pkgs[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pkgs[name] = None
    commit = None
    root = Path(__file__).resolve().parents[2]
    if (root / ".git").exists():
        try:
            commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                                    timeout=10).stdout.strip() or None
        except (OSError, subprocess.SubprocessError):
            commit = None
    devices = {"audio": None}
    if backend != "headless":
        devices["audio"] = audio_device or "system default"
    return {"code": {"version": pkgs.get("sonicverse"), "commit": commit}, "packages": pkgs,
            "python": sys.version.split()[0], "platform": platform.platform(), "backend": backend,
            "simulated_participant": simulated, "devices": devices, "hrtf_set": "kemar"}


class StudyRunner:
    """Runs (or resumes) one session. ``on_event(kind, payload)`` hears: trial_started, trial_done, break, paused,
    aborted, finished (from the running thread)."""

    def __init__(self, store, study, pid: str, session: int, backend: str = "headless", controls=None,
                 on_event=None, audio_device=None):
        from app.study.trials import TrialRunner

        s = store.session(pid, session)
        if s["study_sha"] != study.sha256:
            raise StudyError(f"session {session} of '{pid}' was run with another version of study '{s['study']}' "
                             f"(sha256 {s['study_sha'][:12]}); resume it with that file (its copy is in "
                             f"{store.session_dir(pid, session) / 'study.toml'})")
        self.store, self.study, self.pid, self.session, self.backend = store, study, pid, session, backend
        self.controls = controls or Controls()
        self.on_event = on_event or (lambda kind, payload: None)
        self.trials = TrialRunner(study, store, pid, session, backend, audio_device)

    def plan_state(self) -> tuple[list, set]:
        return self.store.plan(self.pid, self.session), self.store.finished_slots(self.pid, self.session)

    def run(self) -> dict:
        st, pid, n = self.store, self.pid, self.session
        st.reconcile_csv(pid, n)
        plan, done = self.plan_state()
        todo = [s for s in plan if s.slot not in done]
        if done or any(e["kind"] in ("started", "paused") for e in st.events(pid, n)):  # it ran before
            st.event(pid, n, "resume", json.dumps({"first_slot": todo[0].slot if todo else None,
                                                   "done": len(done)}))
        prev = max((s.block for s in plan if s.slot in done), default=None)
        try:
            for slot in todo:
                check_stopped()  # SIGTERM whose raise something swallowed in the last trial: stop before the next
                if prev is not None and slot.block != prev and self.study.break_s > 0:
                    self._break(slot)
                if self.controls.paused:
                    st.event(pid, n, "paused", slot=slot.slot)
                    self.on_event("paused", {"slot": slot.slot})
                    self.controls.wait()
                    if not self.controls.abort_reason:
                        st.event(pid, n, "continued", slot=slot.slot)
                if self.controls.abort_reason:
                    raise TrialAborted(self.controls.abort_reason)
                self._trial(slot, len(plan))
                prev = slot.block
        except BaseException as exc:
            reason = _stop_reason(exc)
            if reason is None:
                raise
            self.on_event("aborted", {"reason": reason})
            raise Interrupted(f"{reason}: the running trial was not kept; continue with `sonicverse study resume "
                              f"--participant {pid} --data {st.root}`") from None
        finally:
            self.trials.close()
        st.set_status(pid, n, "finished")
        flags = self.quality_report()
        st.event(pid, n, "finished", json.dumps({"quality_flags": flags}))
        res = {"participant": pid, "session": n, "trials": len(st.trials(pid, n)), "quality_flags": flags,
               "order": st.order(pid, n)}
        self.on_event("finished", res)
        return res

    def _break(self, slot) -> None:
        st = self.store
        if self.backend == "headless":
            st.event(self.pid, self.session, "break", f"{self.study.break_s:g} s break before block "
                     f"{slot.block}: not taken (simulated participant)", slot.slot)
            return
        st.event(self.pid, self.session, "break", f"{self.study.break_s:g} s break before block {slot.block}",
                 slot.slot)
        self.controls.pause()
        self.on_event("break", {"slot": slot.slot, "seconds": self.study.break_s})

    def _trial(self, slot, total: int) -> None:
        from app.study.store import now_wall

        st = self.store
        started, t0 = now_wall(), time.monotonic()
        st.event(self.pid, self.session, "started", slot.condition, slot.slot)
        self.on_event("trial_started", {**slot.as_dict(), "total": total})
        try:
            metrics, quality, raw = self.trials.run(slot, self.controls.check)
            status = metrics.pop("_status", "done")  # or no_response: a person's trial that timed out
        except TrialSkipped:
            metrics, quality, raw, status = {}, {}, {}, "skipped"
        except BaseException as exc:
            reason = _stop_reason(exc)
            if reason is None:
                raise
            st.event(self.pid, self.session, "aborted", reason, slot.slot)
            raise
        with _signals_held():
            row = st.commit_trial(self.pid, self.session, slot, status, metrics, quality, raw, started,
                                  time.monotonic() - t0)
        self.on_event("trial_done", {**row, "metrics": metrics, "quality": quality, "total": total})

    def quality_report(self) -> list[str]:
        """Warnings for trials whose missed frames, xruns or audio latency passed the study's thresholds."""
        from app.study.trials import quality_flags

        out = []
        for t in self.store.trials(self.pid, self.session):
            for f in quality_flags(t["quality"], self.study.quality):
                out.append(f"block {t['block']} trial {t['trial']}: {f}")
        return out


def start_session(store, study, pid: str, backend: str = "headless", simulated: bool = True,
                  audio_device=None, identity: dict | None = None) -> int:
    """A new session for ``pid`` (enrolled first if new); refuses while the participant has an unfinished one."""
    from app.study.trials import require_backend

    require_backend(backend, simulated)
    if not any(p["id"] == pid for p in store.participants()):
        store.add_participant(pid, identity)
    return store.create_session(study, pid, backend, simulated, manifest(backend, simulated, audio_device))
