"""Study data that survives: SQLite in WAL mode with ``synchronous=FULL`` (a committed transaction survives a
SIGKILL of the process and a power cut), each trial committed in one transaction when it ends; per session a CSV
appended, flushed and fsynced per trial (after the commit), the study file as run and a manifest (replaced
atomically). Nothing is overwritten: a participant's next session gets the next number, a trial slot is committed
once (its primary key), and a CSV that a kill left behind the database is rewritten from it (atomically) before the
session goes on.

Layout under the data folder (default ``./study-data``)::

    study.sqlite (+ -wal, -shm)     participants, sessions, frozen plans, trials, events
    private/identities.csv          identifying details, if any (kept apart from the pseudonymous data)
    P001/session-1/trials.csv       one row per finished trial
    P001/session-1/manifest.json    study hash, code version, seeds, conditions, devices, package versions
    P001/session-1/study.toml       the study file as run
    P001/session-1/raw/             per-trial raw data (trajectories)
"""
from __future__ import annotations

import csv
import io
import json
import os
import re
import sqlite3
import threading
import time
from datetime import datetime, timezone
from pathlib import Path

from app.study.design import Slot, assign_row, session_plan, williams
from sonicverse_core.errors import StudyError

PID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_-]{0,31}$")
CSV_KEYS = ("participant", "session", "block", "block_name", "trial", "condition", "task", "practice", "status",
            "t_mono", "t_wall", "duration_s", "metrics", "quality", "raw")

SCHEMA = """
CREATE TABLE IF NOT EXISTS participants (
    id TEXT PRIMARY KEY, enrol INTEGER UNIQUE NOT NULL, created_wall TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS sessions (
    participant TEXT NOT NULL REFERENCES participants(id), session INTEGER NOT NULL, study TEXT NOT NULL,
    study_sha TEXT NOT NULL, order_row INTEGER NOT NULL, order_json TEXT NOT NULL, status TEXT NOT NULL,
    backend TEXT NOT NULL, simulated INTEGER NOT NULL, created_wall TEXT NOT NULL, finished_wall TEXT,
    PRIMARY KEY (participant, session));
CREATE TABLE IF NOT EXISTS plan (
    participant TEXT NOT NULL, session INTEGER NOT NULL, slot INTEGER NOT NULL, block INTEGER NOT NULL,
    block_name TEXT NOT NULL, task TEXT NOT NULL, condition TEXT NOT NULL, trial INTEGER NOT NULL,
    practice INTEGER NOT NULL, seed INTEGER NOT NULL, PRIMARY KEY (participant, session, slot));
CREATE TABLE IF NOT EXISTS trials (
    participant TEXT NOT NULL, session INTEGER NOT NULL, slot INTEGER NOT NULL, block INTEGER NOT NULL,
    block_name TEXT NOT NULL, trial INTEGER NOT NULL, condition TEXT NOT NULL, task TEXT NOT NULL,
    practice INTEGER NOT NULL, status TEXT NOT NULL, metrics TEXT NOT NULL, quality TEXT NOT NULL, raw TEXT NOT NULL,
    t_mono REAL NOT NULL, t_wall TEXT NOT NULL, started_wall TEXT NOT NULL, duration_s REAL NOT NULL,
    PRIMARY KEY (participant, session, slot));
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY AUTOINCREMENT, participant TEXT, session INTEGER, slot INTEGER, kind TEXT NOT NULL,
    detail TEXT NOT NULL, t_mono REAL NOT NULL, t_wall TEXT NOT NULL);
"""


def now_wall() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class StudyStore:
    """One data folder. Safe to use from several threads (a connection per thread)."""

    def __init__(self, data_dir: str | Path = "study-data", create: bool = True):
        self.root = Path(data_dir)
        if self.root.exists() and not self.root.is_dir():
            raise StudyError(f"the data folder '{self.root}' is a file")
        if not create and not (self.root / "study.sqlite").is_file():
            raise StudyError(f"no study data in '{self.root}' (give the --data folder a study ran with)")
        self.root.mkdir(parents=True, exist_ok=True)
        self.path = self.root / "study.sqlite"
        self._local = threading.local()
        self._db().executescript(SCHEMA)  # (executescript commits by itself)

    # --- the database -----------------------------------------------------------------------------------------
    def _db(self) -> sqlite3.Connection:
        db = getattr(self._local, "db", None)
        if db is None:
            try:
                db = sqlite3.connect(self.path, isolation_level=None, timeout=30.0)
                db.execute("PRAGMA journal_mode=WAL")
                db.execute("PRAGMA synchronous=FULL")
                db.execute("PRAGMA foreign_keys=ON")
            except sqlite3.DatabaseError as exc:
                raise StudyError(f"'{self.path}' is not a study database ({exc})") from None
            db.row_factory = sqlite3.Row
            self._local.db = db
        return db

    class _Tx:
        def __init__(self, db):
            self.db = db

        def __enter__(self):
            self.db.execute("BEGIN IMMEDIATE")
            return self.db

        def __exit__(self, et, ev, tb):
            self.db.execute("COMMIT" if et is None else "ROLLBACK")
            return False

    def _tx(self):
        return self._Tx(self._db())

    def close(self) -> None:
        db = getattr(self._local, "db", None)
        if db is not None:
            db.close()
            self._local.db = None

    def event(self, participant: str | None, session: int | None, kind: str, detail: str = "",
              slot: int | None = None) -> None:
        with self._tx() as db:
            db.execute("INSERT INTO events (participant, session, slot, kind, detail, t_mono, t_wall) "
                       "VALUES (?, ?, ?, ?, ?, ?, ?)", (participant, session, slot, kind, detail, time.monotonic(),
                                                        now_wall()))

    def events(self, participant: str, session: int | None = None) -> list[dict]:
        q = "SELECT * FROM events WHERE participant = ?" + (" AND session = ?" if session is not None else "")
        args = (participant,) if session is None else (participant, session)
        return [dict(r) for r in self._db().execute(q + " ORDER BY id", args)]

    # --- participants -----------------------------------------------------------------------------------------
    def participants(self) -> list[dict]:
        return [dict(r) for r in self._db().execute("SELECT * FROM participants ORDER BY enrol")]

    def participant(self, pid: str) -> dict:
        r = self._db().execute("SELECT * FROM participants WHERE id = ?", (pid,)).fetchone()
        if r is None:
            raise StudyError(f"no participant '{pid}' in {self.root} (create one with `sonicverse study run ... "
                             f"--participant {pid}` or in the launcher)")
        return dict(r)

    def add_participant(self, pid: str, identity: dict | None = None) -> dict:
        """Enrol a participant (the next enrolment index). ``identity``: identifying details, written to
        ``private/identities.csv`` only, never beside the data."""
        if not PID.match(pid or ""):
            raise StudyError(f"participant id must be 1-32 letters, digits, - or _ (pseudonymous), got {pid!r}")
        with self._tx() as db:
            if db.execute("SELECT 1 FROM participants WHERE id = ?", (pid,)).fetchone():
                raise StudyError(f"participant '{pid}' exists already; pick another id")
            enrol = int(db.execute("SELECT COALESCE(MAX(enrol), 0) + 1 FROM participants").fetchone()[0])
            db.execute("INSERT INTO participants VALUES (?, ?, ?)", (pid, enrol, now_wall()))
        if identity:
            priv = self.root / "private"
            priv.mkdir(exist_ok=True)
            p = priv / "identities.csv"
            new = not p.exists()
            with open(p, "a", newline="", encoding="utf-8") as fh:
                w = csv.writer(fh)
                if new:
                    w.writerow(["participant", "details", "t_wall"])
                w.writerow([pid, json.dumps(identity, ensure_ascii=False), now_wall()])
                fh.flush()
                os.fsync(fh.fileno())
        return self.participant(pid)

    # --- sessions ---------------------------------------------------------------------------------------------
    def sessions(self, pid: str) -> list[dict]:
        return [dict(r) for r in self._db().execute(
            "SELECT * FROM sessions WHERE participant = ? ORDER BY session", (pid,))]

    def session(self, pid: str, session: int | None = None) -> dict:
        """A session, or the participant's latest."""
        rows = self.sessions(pid)
        if session is not None:
            rows = [r for r in rows if r["session"] == session]
        if not rows:
            raise StudyError(f"participant '{pid}' has no session {session}" if session is not None
                             else f"participant '{pid}' has no session yet")
        return rows[-1]

    def unfinished(self, pid: str) -> dict | None:
        rows = [r for r in self.sessions(pid) if r["status"] != "finished"]
        return rows[-1] if rows else None

    def session_dir(self, pid: str, session: int) -> Path:
        return self.root / pid / f"session-{session}"

    def create_session(self, study, pid: str, backend: str, simulated: bool, manifest: dict) -> int:
        """A new session for ``pid`` with its condition order and plan frozen; refuses while one is unfinished."""
        part = self.participant(pid)
        with self._tx() as db:
            open_ = db.execute("SELECT session FROM sessions WHERE participant = ? AND status != 'finished'",
                               (pid,)).fetchone()
            if open_ is not None:
                raise StudyError(f"participant '{pid}' has an unfinished session {open_[0]}; continue it with "
                                 f"`sonicverse study resume --participant {pid}`")
            n = int(db.execute("SELECT COALESCE(MAX(session), 0) + 1 FROM sessions WHERE participant = ?",
                               (pid,)).fetchone()[0])
            counts = {int(r[0]): int(r[1]) for r in db.execute(
                "SELECT order_row, COUNT(*) FROM sessions WHERE study = ? AND status = 'finished' GROUP BY order_row",
                (study.name,))}
            row = assign_row(study.counterbalance, len(study.conditions), part["enrol"], counts)
            order = [study.conditions[i].name for i in williams(len(study.conditions))[row]]
            plan = session_plan(study, order, part["enrol"], n)
            db.execute("INSERT INTO sessions VALUES (?, ?, ?, ?, ?, ?, 'running', ?, ?, ?, NULL)",
                       (pid, n, study.name, study.sha256, row, json.dumps(order), backend, int(simulated),
                        now_wall()))
            db.executemany("INSERT INTO plan VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                           [(pid, n, s.slot, s.block, s.block_name, s.task, s.condition, s.trial, int(s.practice),
                             s.seed) for s in plan])
        d = self.session_dir(pid, n)
        (d / "raw").mkdir(parents=True, exist_ok=True)
        from sonicverse_core.storage import write_text_atomic

        write_text_atomic(d / "study.toml", study.text)
        write_text_atomic(d / "manifest.json", json.dumps(
            {**manifest, "participant": pid, "session": n, "enrol": part["enrol"], "study": study.name,
             "study_sha256": study.sha256, "study_source": study.source, "counterbalance": study.counterbalance,
             "order_row": row, "condition_order": order,
             "conditions": {c.name: c.as_dict() for c in study.conditions},
             "seeds": {"study": study.seed, "slots": [s.seed for s in plan]}, "created_wall": now_wall()},
            indent=1))
        self._rewrite_csv(pid, n)
        self.event(pid, n, "created", json.dumps({"order": order, "row": row, "backend": backend}))
        return n

    def set_status(self, pid: str, session: int, status: str) -> None:
        with self._tx() as db:
            db.execute("UPDATE sessions SET status = ?, finished_wall = ? WHERE participant = ? AND session = ?",
                       (status, now_wall() if status == "finished" else None, pid, session))

    def order(self, pid: str, session: int) -> list[str]:
        return json.loads(self.session(pid, session)["order_json"])

    def plan(self, pid: str, session: int) -> list[Slot]:
        return [Slot(r["slot"], r["block"], r["block_name"], r["task"], r["condition"], r["trial"],
                     bool(r["practice"]), r["seed"]) for r in self._db().execute(
            "SELECT * FROM plan WHERE participant = ? AND session = ? ORDER BY slot", (pid, session))]

    # --- trials -----------------------------------------------------------------------------------------------
    def trials(self, pid: str | None = None, session: int | None = None, status: str | None = "done") -> list[dict]:
        q, args = "SELECT * FROM trials WHERE 1 = 1", []
        for col, v in (("participant", pid), ("session", session), ("status", status)):
            if v is not None:
                q += f" AND {col} = ?"
                args.append(v)
        rows = []
        for r in self._db().execute(q + " ORDER BY participant, session, slot", args):
            d = dict(r)
            for k in ("metrics", "quality", "raw"):
                d[k] = json.loads(d[k])
            d["practice"] = bool(d["practice"])
            rows.append(d)
        return rows

    def finished_slots(self, pid: str, session: int) -> set[int]:
        return {int(r[0]) for r in self._db().execute(
            "SELECT slot FROM trials WHERE participant = ? AND session = ?", (pid, session))}

    def commit_trial(self, pid: str, session: int, slot: Slot, status: str, metrics: dict, quality: dict,
                     raw: dict, started_wall: str, duration_s: float) -> dict:
        """The trial in one transaction (it is then safe), then its CSV row appended and fsynced."""
        row = {"participant": pid, "session": session, "slot": slot.slot, "block": slot.block,
               "block_name": slot.block_name, "trial": slot.trial, "condition": slot.condition, "task": slot.task,
               "practice": int(slot.practice), "status": status, "metrics": json.dumps(metrics, default=_plain),
               "quality": json.dumps(quality, default=_plain), "raw": json.dumps(raw), "t_mono": time.monotonic(),
               "t_wall": now_wall(), "started_wall": started_wall, "duration_s": round(float(duration_s), 4)}
        with self._tx() as db:
            db.execute(f"INSERT INTO trials ({', '.join(row)}) VALUES ({', '.join('?' * len(row))})",
                       tuple(row.values()))
        self._append_csv(pid, session, row)
        return row

    # --- the session's CSV ------------------------------------------------------------------------------------
    def csv_path(self, pid: str, session: int) -> Path:
        return self.session_dir(pid, session) / "trials.csv"

    @staticmethod
    def _csv_row(row: dict) -> dict:
        return {k: row[k] for k in CSV_KEYS}

    def _append_csv(self, pid: str, session: int, row: dict) -> None:
        with open(self.csv_path(pid, session), "a", newline="", encoding="utf-8") as fh:
            csv.DictWriter(fh, fieldnames=CSV_KEYS).writerow(self._csv_row(row))
            fh.flush()
            os.fsync(fh.fileno())

    def _rewrite_csv(self, pid: str, session: int) -> None:
        from sonicverse_core.storage import write_text_atomic

        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=CSV_KEYS)
        w.writeheader()
        for r in self._db().execute("SELECT * FROM trials WHERE participant = ? AND session = ? ORDER BY slot",
                                    (pid, session)):
            w.writerow(self._csv_row(dict(r)))
        write_text_atomic(self.csv_path(pid, session), buf.getvalue())
        _fsync_dir(self.session_dir(pid, session))

    def reconcile_csv(self, pid: str, session: int) -> bool:
        """Make the session's CSV hold exactly the database's trials (a kill between the commit and the append, or
        in the middle of a line, leaves it behind); True when it had to be rewritten."""
        p = self.csv_path(pid, session)
        want = sorted(self.finished_slots(pid, session))
        slot_of = {(s.block, s.trial): s.slot for s in self.plan(pid, session)}
        try:
            with open(p, newline="", encoding="utf-8") as fh:
                text = fh.read()
            rows = list(csv.DictReader(io.StringIO(text)))
            ok = text.endswith("\n") and len(rows) == len(want) and \
                [slot_of.get((int(r["block"]), int(r["trial"]))) for r in rows] == want
        except (OSError, csv.Error, KeyError, ValueError):
            ok = False
        if not ok:
            self._rewrite_csv(pid, session)
            self.event(pid, session, "csv_rewritten", f"{len(want)} trials from the database")
        return not ok


def _plain(o):
    if hasattr(o, "tolist"):
        return o.tolist()
    if hasattr(o, "item"):
        return o.item()
    return str(o)
