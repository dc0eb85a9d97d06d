"""Poses handed from the main loop (frame rate) to the audio callback (block rate), and their interpolation.

One frame of poses is a float64 vector (see :class:`PoseLayout`): the main loop's time, the user's head (position,
yaw, pitch), both hands, the sidetone gain, each robot listener (position, yaw), each scene source (position,
gain) and each door's open fraction. The audio side does not jump to a new frame: it ramps from where it is to the
new frame over the measured frame interval, so a 90 Hz head pose drives a 187.5 Hz block clock smoothly. Yaw is
interpolated the short way round; an entity that moved more than ``teleport_m`` between frames jumps.
"""
from __future__ import annotations

import math

import numpy as np

from sonicverse_core.acoustics.kernels import lerp
from sonicverse_core.errors import PoseError

MOUTH_OFFSET = np.array([0.08, 0.0, -0.07])  # m in the head frame (x forward, z up): in front of and below the ears


class PoseLayout:
    def __init__(self, n_robots: int = 0, n_sources: int = 0, n_doors: int = 0):
        self.n_robots, self.n_sources, self.n_doors = n_robots, n_sources, n_doors
        self.T, self.HEAD, self.HANDS, self.SIDETONE = 0, slice(1, 6), slice(6, 12), 12
        o = 13
        self.ROBOTS = slice(o, o + 4 * n_robots)
        o += 4 * n_robots
        self.SOURCES = slice(o, o + 3 * n_sources)
        o += 3 * n_sources
        self.GAINS = slice(o, o + n_sources)
        o += n_sources
        self.DOORS = slice(o, o + n_doors)
        self.size = o + n_doors
        angles = [4, 5] + [self.ROBOTS.start + 4 * k + 3 for k in range(n_robots)]
        self.angle_idx = np.array(angles, np.int64)
        # entities whose position may teleport: (start index of xyz)
        self.entities = np.array([1, 6, 9] + [self.ROBOTS.start + 4 * k for k in range(n_robots)]
                                 + [self.SOURCES.start + 3 * k for k in range(n_sources)], np.int64)

    def frame(self, t: float, head, hands=None, robots=(), sources=(), gains=None, doors=(),
              sidetone: float = 0.0) -> np.ndarray:
        """Validate and pack one frame. head: (x, y, z, yaw[, pitch]); robots: (x, y, z, yaw) each;
        sources: (x, y, z) each; doors: open fraction in [0, 1] each."""
        v = np.zeros(self.size)
        v[self.T] = t
        head = np.asarray(head, float).ravel()
        if head.size not in (4, 5):
            raise PoseError(f"head pose must be x, y, z, yaw[, pitch], got {head.size} numbers")
        v[1:1 + head.size] = head
        if hands is not None:
            v[self.HANDS] = np.asarray(hands, float).ravel()
        v[self.SIDETONE] = sidetone
        for name, sl, val, width in (("robot", self.ROBOTS, robots, 4), ("source", self.SOURCES, sources, 3)):
            a = np.asarray(val, float).reshape(-1, width) if len(val) else np.zeros((0, width))
            if a.shape[0] != (sl.stop - sl.start) // width:
                raise PoseError(f"expected {(sl.stop - sl.start) // width} {name} poses, got {a.shape[0]}")
            v[sl] = a.ravel()
        v[self.GAINS] = 1.0 if gains is None else np.asarray(gains, float)
        d = np.asarray(doors, float).ravel()
        if d.size != self.n_doors:
            raise PoseError(f"expected {self.n_doors} door fractions, got {d.size}")
        v[self.DOORS] = d
        if not np.all(np.isfinite(v)):
            raise PoseError("a pose handed to the audio thread is not finite (NaN or infinity)")
        if np.any(d < 0) or np.any(d > 1) or np.any(v[self.GAINS] < 0) or not (0 <= sidetone <= 4):
            raise PoseError("door fractions must be in [0, 1], source gains >= 0, sidetone in [0, 4]")
        return v


def wrap180(a):
    return (a + 180.0) % 360.0 - 180.0


class PoseInterpolator:
    """Audio-side pose state: ``advance(block_s)`` once per block returns the pose vector to render with."""

    def __init__(self, layout: PoseLayout, teleport_m: float = 1.0):
        self.L, self.teleport = layout, teleport_m
        n = layout.size
        self.cur, self.start, self.target = np.zeros(n), np.zeros(n), np.zeros(n)
        self.frac, self.interval, self.last_t, self.started = 1.0, 1 / 90, None, False

    def new_frame(self, v: np.ndarray, interval: float | None = None) -> None:
        """A new target pose frame; the ramp towards it lasts the measured frame interval (smoothed), or
        ``interval`` seconds when the caller knows it (the offline renderer of the frame clock). An entity that
        moved more than ``teleport_m`` jumps instead of sweeping through the scene."""
        if not self.started:  # the first frame is taken as it is
            self.cur[:] = v
            self.start[:] = v
            self.target[:] = v
            self.started, self.last_t = True, v[0]
            return
        dt = v[0] - self.last_t
        if interval is not None:
            self.interval = float(interval)
        elif 0 < dt < 0.25:  # frame interval, smoothed; a stall or a clock reset is ignored
            self.interval += 0.2 * (dt - self.interval)
        self.last_t = v[0]
        self.start[:] = self.cur
        self.target[:] = v
        t, s0 = self.target, self.start
        for a in self.L.angle_idx:  # element by element: the callback reads frames, and allocates nothing
            t[a] = s0[a] + wrap180(v[a] - s0[a])
        for e in self.L.entities:
            dx, dy, dz = t[e] - s0[e], t[e + 1] - s0[e + 1], t[e + 2] - s0[e + 2]
            if dx * dx + dy * dy + dz * dz > self.teleport * self.teleport:
                s0[e], s0[e + 1], s0[e + 2] = t[e], t[e + 1], t[e + 2]
        self.frac = 0.0

    def advance(self, block_s: float) -> np.ndarray:
        if self.frac < 1.0:
            self.frac = min(1.0, self.frac + block_s / max(self.interval, block_s))
            lerp(self.start, self.target, self.frac, self.cur)
        return self.cur


def mouth(head: np.ndarray, out: tuple | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mouth position and facing direction for a head pose (x, y, z, yaw, pitch); written into ``out`` (two
    (3,) arrays) when given."""
    yaw, pitch = math.radians(head[3]), math.radians(head[4])
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    fwd = (cy * cp, sy * cp, sp)
    left = (-sy, cy, 0.0)
    up = (fwd[1] * left[2] - fwd[2] * left[1], fwd[2] * left[0] - fwd[0] * left[2],
          fwd[0] * left[1] - fwd[1] * left[0])
    pos, f = out if out is not None else (np.empty(3), np.empty(3))
    o0, o1, o2 = float(MOUTH_OFFSET[0]), float(MOUTH_OFFSET[1]), float(MOUTH_OFFSET[2])
    for k in range(3):
        pos[k] = head[k] + o0 * fwd[k] + o1 * left[k] + o2 * up[k]
        f[k] = fwd[k]
    return pos, f
