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

from sonicverse_core.errors import ConfigError, DataError

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


class Recording:
    """Frame inputs of a session, saved as one .npz (arrays + a JSON header)."""

    VERSION = 1

    def __init__(self, meta: dict | None = None):
        self.meta = dict(meta or {})
        self.frames: list[FrameInput] = []

    def add(self, f: FrameInput) -> None:
        self.frames.append(FrameInput(f.index, f.t, f.dt, f.head.copy(), f.hands.copy(), f.hands_valid.copy(),
                                      f.buttons.copy(), f.quit))

    def save(self, path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fr = self.frames
        with open(path, "wb") as fh:
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
        try:
            with np.load(path, allow_pickle=False) as z:
                meta = json.loads(str(z["header"]))
                arrays = {k: z[k] for k in ("t", "dt", "head", "hands", "hands_valid", "buttons")}
        except (OSError, ValueError, KeyError) as exc:
            raise DataError(f"'{path}' is not a Sonicverse input recording ({exc})") from None
        if meta.get("version") != cls.VERSION:
            raise DataError(f"'{path}': recording version {meta.get('version')} is not {cls.VERSION}")
        rec = cls(meta)
        for k in range(len(arrays["t"])):
            rec.frames.append(FrameInput(k, float(arrays["t"][k]), float(arrays["dt"][k]), arrays["head"][k],
                                         arrays["hands"][k], arrays["hands_valid"][k], arrays["buttons"][k]))
        for f in rec.frames:
            if not (np.all(np.isfinite(f.head)) and np.all(np.isfinite(f.hands)) and np.isfinite(f.dt) and f.dt > 0):
                raise DataError(f"'{path}': frame {f.index} has a non-finite pose or a non-positive time step")
        return rec
