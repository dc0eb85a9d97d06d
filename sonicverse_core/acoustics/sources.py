"""What a renderer renders from and for: its sources (position, gain, forward, live blocks; views onto the
renderer's arrays) and listeners (pose), and the helper that grows their per-source arrays."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sonicverse_core.errors import ConfigError, PoseError

MAX_GAIN = 1e6  # +120 dB: a larger source gain would overflow the float32 signal path


class Source:
    """A sound source owned by a renderer. Set ``position`` (3,), ``gain``, ``forward`` (3,) at any time.
    directivity alpha in [0, 1] and sharpness >= 1; spread in degrees (0 point, 360 fully diffuse).
    Live sources take blocks with :meth:`push` (missing blocks play silence)."""

    def __init__(self, renderer, index: int, live: bool, attached_to: str | None):
        self._r, self.index, self.live, self.attached_to = renderer, index, live, attached_to
        self.pending: np.ndarray | None = None

    @property
    def position(self) -> np.ndarray:
        return self._r._pos[self.index].copy()

    @position.setter
    def position(self, p) -> None:
        p = np.asarray(p, float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise PoseError(f"source position must be 3 finite numbers, got {p}")
        self._r._pos[self.index] = p

    @property
    def gain(self) -> float:
        return float(self._r._gain[self.index])

    @gain.setter
    def gain(self, g: float) -> None:
        if not np.isfinite(g) or not 0 <= g <= MAX_GAIN:
            raise ConfigError(f"source gain must be within 0..{MAX_GAIN:g}, got {g}")
        self._r._gain[self.index] = g

    @property
    def forward(self) -> np.ndarray:
        return self._r._fwd[self.index].copy()

    @forward.setter
    def forward(self, v) -> None:
        v = np.asarray(v, float)
        n = np.linalg.norm(v) if v.shape == (3,) else 0.0
        if not np.isfinite(n) or n < 1e-9:
            raise PoseError(f"source forward must be a finite nonzero 3-vector, got {v}")
        self._r._fwd[self.index] = v / n

    def push(self, block: np.ndarray) -> None:
        """The next block of a live source (a microphone): non-finite samples become zeros (counted in the
        renderer's ``stats["nonfinite_input"]``), magnitudes are clipped to 1e6."""
        block = np.asarray(block, np.float32).ravel()
        if len(block) != self._r.cfg.block:
            raise ConfigError(f"a live block must have {self._r.cfg.block} frames, got {len(block)}")
        if not np.isfinite(block).all():
            self._r.stats["nonfinite_input"] += 1
            block = np.nan_to_num(block, nan=0.0, posinf=0.0, neginf=0.0)
        self.pending = np.clip(block, -MAX_GAIN, MAX_GAIN)


@dataclass
class Listener:
    position: np.ndarray
    yaw: float = 0.0  # degrees, 0 faces +x, 90 faces +y
    pitch: float = 0.0  # degrees, positive looks up

    def rotation(self) -> np.ndarray:
        """World -> head frame (x forward, y left, z up) rotation matrix (3, 3): yaw about z, then pitch."""
        c, s = np.cos(np.radians(self.yaw)), np.sin(np.radians(self.yaw))
        cp, sp = np.cos(np.radians(self.pitch)), np.sin(np.radians(self.pitch))
        return np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]]) @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1.0]])


def grown(old: np.ndarray | None, shape: tuple, dtype, fill=0) -> np.ndarray:
    """A new array of ``shape`` filled with ``fill`` whose leading rows are a copy of ``old``."""
    new = np.full(shape, fill, dtype)
    if old is not None:
        new[: len(old)] = old
    return new
