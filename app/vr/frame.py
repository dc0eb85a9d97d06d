"""What one frame of input is (the same for every backend), frame timing statistics, and input recordings.

A backend turns its devices (a headset, a mouse and keyboard, a script) into :class:`FrameInput`; the loop never
sees anything else, so task code runs unchanged on all of them, and a recording of these inputs replayed through
the headless backend gives the same simulation trajectory.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sonicverse_core.errors import ConfigError, DataError, stop_held

# button bits, as in OpenVR's ulButtonPressed (k_EButton_*): desktop keys and scripts use the same masks
BUTTON_MENU = 1 << 1
BUTTON_GRIP = 1 << 2
BUTTON_TRIGGER = 1 << 33
LEFT, RIGHT = 0, 1


@dataclass
class FrameInput:
    """One frame of tracking and input. Poses are 4x4 device -> world (z up) in the camera convention (x right,
    y up, looking along -z). ``t`` is the simulation time of the frame, ``dt`` the step since the last one (s)."""

    index: int
    t: float
    dt: float
    head: np.ndarray
    hands: np.ndarray = field(default_factory=lambda: np.tile(np.eye(4), (2, 1, 1)))
    hands_valid: np.ndarray = field(default_factory=lambda: np.zeros(2, bool))
    buttons: np.ndarray = field(default_factory=lambda: np.zeros(2, np.uint64))
    quit: bool = False

    def pressed(self, hand: int, mask: int) -> bool:
        return bool(int(self.buttons[hand]) & mask)


class FrameStats:
    """Frame-to-frame intervals against a target rate, like PsychoPy's dropped-frame check: an interval of about
    k periods means k - 1 refreshes were missed (an interval longer than 1.5 periods counts round(i / T) - 1)."""

    def __init__(self, target_hz: float):
        if not (1 <= target_hz <= 1000):
            raise ConfigError(f"target frame rate must be 1-1000 Hz, got {target_hz}")
        self.target_hz = float(target_hz)
        self.intervals: list[float] = []
        self.work: list[float] = []

    def add(self, interval_s: float, work_s: float) -> None:
        self.intervals.append(interval_s)
        self.work.append(work_s)

    def missed(self) -> int:
        T = 1.0 / self.target_hz
        i = np.asarray(self.intervals)
        late = i[i > 1.5 * T]
        return int(np.sum(np.round(late / T) - 1))

    def histogram(self, bins_ms=None) -> dict:
        T = 1000.0 / self.target_hz
        edges = np.asarray(bins_ms if bins_ms is not None else
                           [0, 0.5 * T, 0.9 * T, 1.1 * T, 1.5 * T, 2.5 * T, 4 * T, 1e9])
        counts, _ = np.histogram(np.asarray(self.intervals) * 1000, edges)
        return {"edges_ms": [round(float(e), 3) for e in edges[:-1]] + ["inf"], "counts": counts.tolist()}

    def summary(self) -> dict:
        i = np.asarray(self.intervals) * 1000
        w = np.asarray(self.work) * 1000
        q = (lambda a, p: round(float(np.percentile(a, p)), 3) if a.size else None)
        return {"frames": len(self.intervals), "missed_frames": self.missed() if self.intervals else 0,
                "frame_ms_p50": q(i, 50), "frame_ms_p99": q(i, 99), "frame_ms_max": q(i, 100),
                "work_ms_p50": q(w, 50), "work_ms_p99": q(w, 99), "target_hz": self.target_hz,
                "fps": round(len(i) / (i.sum() / 1000), 2) if i.size and i.sum() > 0 else None,
                "histogram": self.histogram()}


FRAME_DTYPE = np.dtype([("t", "<f8"), ("dt", "<f8"), ("head", "<f8", (4, 4)), ("hands", "<f8", (2, 4, 4)),
                        ("hands_valid", "?", (2,)), ("buttons", "<u8", (2,))])


class Recording:
    """Frame inputs of a session. Written while the session runs as an append-only ``.svrec`` (a record log:
    a kill loses at most the last second), or saved at the end as one ``.npz``; :meth:`load` reads both."""

    VERSION = 1
    ARRAYS = ("t", "dt", "head", "hands", "hands_valid", "buttons")

    def __init__(self, meta: dict | None = None):
        self.meta = dict(meta or {})
        self.frames: list[FrameInput] = []
        self._logs: list = []  # RecordLogs that get every frame as it is added

    def add(self, f: FrameInput) -> None:
        """The frame into the list and every log it streams to, or into none: a stop (SIGTERM) raised between the
        two would leave the ``.npz`` saved at the end a frame longer than the ``.svrec``."""
        frame = FrameInput(f.index, f.t, f.dt, f.head.copy(), f.hands.copy(), f.hands_valid.copy(), f.buttons.copy(),
                           f.quit)
        with stop_held():
            self.frames.append(frame)
            for log in self._logs:
                log.append((f.t, f.dt, f.head, f.hands, f.hands_valid, f.buttons))

    def stream_to(self, path, sync_every: int = 90) -> Path:
        """From now on, append every added frame to the ``.svrec`` file ``path`` (frames already added first),
        synced to the disk every ``sync_every`` frames."""
        from sonicverse_core.storage import RecordLog

        log = RecordLog(path, FRAME_DTYPE, {"format": "sonicverse-input", "version": self.VERSION, **self.meta},
                        sync_every)
        for f in self.frames:
            log.append((f.t, f.dt, f.head, f.hands, f.hands_valid, f.buttons))
        self._logs.append(log)
        return log.path

    def sync(self) -> None:
        for log in self._logs:
            log.sync()

    def close(self) -> None:
        for log in self._logs:
            log.close()
        self._logs = []

    def save(self, path) -> Path:
        """The whole recording as ``.npz`` (replaced atomically) or ``.svrec``."""
        path = Path(path)
        if path.suffix == ".svrec":
            log = next((g for g in self._logs if g.path.resolve() == path.resolve()), None)
            if log is None:
                self.stream_to(path)
            self.sync()
            return path
        from sonicverse_core.storage import atomic_write

        fr = self.frames
        with atomic_write(path) as fh:
            np.savez_compressed(
                fh, header=np.array(json.dumps({"version": self.VERSION, **self.meta})),
                t=np.array([f.t for f in fr]), dt=np.array([f.dt for f in fr]),
                head=np.array([f.head for f in fr]).reshape(-1, 4, 4),
                hands=np.array([f.hands for f in fr]).reshape(-1, 2, 4, 4),
                hands_valid=np.array([f.hands_valid for f in fr]).reshape(-1, 2),
                buttons=np.array([f.buttons for f in fr], np.uint64).reshape(-1, 2))
        return path

    @classmethod
    def load(cls, path) -> "Recording":
        path = Path(path)
        if not path.is_file():
            raise DataError(f"recording '{path}' not found")
        if path.suffix == ".svrec":
            from sonicverse_core.storage import read_records

            meta, rec = read_records(path)
            if meta.pop("format", None) != "sonicverse-input":
                raise DataError(f"'{path}' is a record log, but not an input recording")
            arrays = {k: rec[k] for k in cls.ARRAYS}
        else:
            import zipfile

            try:
                with np.load(path, allow_pickle=False) as z:
                    meta = json.loads(str(z["header"]))
                    arrays = {k: z[k] for k in cls.ARRAYS}
            except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as exc:
                raise DataError(f"'{path}' is not a Sonicverse input recording ({exc})") from None
        if not isinstance(meta, dict) or meta.get("version") != cls.VERSION:
            v = meta.get("version") if isinstance(meta, dict) else None
            raise DataError(f"'{path}': recording version {v} is not {cls.VERSION}")
        n = len(arrays["t"])
        shapes = {"dt": (n,), "head": (n, 4, 4), "hands": (n, 2, 4, 4), "hands_valid": (n, 2), "buttons": (n, 2)}
        for k, shape in shapes.items():
            if arrays[k].shape != shape:
                raise DataError(f"'{path}': '{k}' has shape {arrays[k].shape}, expected {shape} (mismatched arrays)")
        if n == 0:
            raise DataError(f"'{path}' holds no frames")
        rec = cls(meta)
        for k in range(n):
            rec.frames.append(FrameInput(k, float(arrays["t"][k]), float(arrays["dt"][k]), arrays["head"][k],
                                         arrays["hands"][k], arrays["hands_valid"][k].astype(bool),
                                         arrays["buttons"][k].astype(np.uint64)))
        for f in rec.frames:
            if not (np.all(np.isfinite(f.head)) and np.all(np.isfinite(f.hands)) and np.isfinite(f.dt) and f.dt > 0):
                raise DataError(f"'{path}': frame {f.index} has a non-finite pose or a non-positive time step")
        return rec
