"""The headless backend: a scripted or recorded head/hand trajectory on a fixed-step clock.

Frame k has time k / rate exactly and dt = 1 / rate (a recording keeps its own times and steps), so a session is a
pure function of its inputs. ``realtime=True`` paces frames to the wall clock (a soak test of the loop);
otherwise it runs flat out (benchmarks, training, batch evaluation).
"""
from __future__ import annotations

import math
import time

import numpy as np

from app.vr.frame import BUTTON_TRIGGER, RIGHT, FrameInput, Recording
from app.vr.transforms import head_pose, look_matrix
from sonicverse_core.errors import ConfigError

EYE_HEIGHT = 1.6  # m above the floor
WALK_SPEED = 1.0  # m/s


def hand_poses(head: np.ndarray) -> np.ndarray:
    """(2, 4, 4) hands held in front of the body at waist height (left, right), from a head pose."""
    yaw = math.radians(head_pose(head)[3])
    fwd, left = np.array([math.cos(yaw), math.sin(yaw), 0.0]), np.array([-math.sin(yaw), math.cos(yaw), 0.0])
    hands = np.tile(head, (2, 1, 1))
    for k, side in enumerate((0.22, -0.22)):
        hands[k, :3, 3] = head[:3, 3] + 0.35 * fwd + side * left + np.array([0, 0, -0.45])
    return hands


class WalkTrajectory:
    """The user walks the shortest path from ``start`` to ``goal`` at 1 m/s, looking around (+-25 deg at 0.3 Hz),
    and pulls the right trigger for a few frames the first time the right hand comes within reach of a door."""

    def __init__(self, scene, grid, start, goal, rate: float, reach: float = 0.9, speed: float | None = None):
        path, length = grid.shortest_path(start, goal)
        if not math.isfinite(length) or len(path) < 2:
            path, length = np.array([start, start]), 0.0
        self.path, self.length = np.asarray(path, float), length
        seg = np.linalg.norm(np.diff(self.path, axis=0), axis=1)
        self.cum = np.concatenate([[0.0], np.cumsum(seg)])
        self.z = scene.floor_z + EYE_HEIGHT
        self.rate, self.reach = rate, reach
        self.doors = [d.world_bounds(d.pose).mean(axis=0) for d in scene.doors]
        self.pressed_at: int | None = None
        self.speed = WALK_SPEED if speed is None else float(speed)

    def __call__(self, k: int, t: float):
        s = min(self.speed * t, self.length)
        i = int(np.clip(np.searchsorted(self.cum, s, side="right") - 1, 0, len(self.path) - 2))
        seg = self.cum[i + 1] - self.cum[i]
        a = 0.0 if seg <= 0 else (s - self.cum[i]) / seg
        p = self.path[i] + a * (self.path[i + 1] - self.path[i])
        d = self.path[i + 1] - self.path[i]
        heading = math.degrees(math.atan2(d[1], d[0])) if seg > 0 else 0.0
        yaw = heading + 25.0 * math.sin(2 * math.pi * 0.3 * t)
        head = look_matrix(p[0], p[1], self.z, yaw, -5.0)
        hands = hand_poses(head)
        buttons = np.zeros(2, np.uint64)
        if self.pressed_at is None and self.doors:
            near = min(float(np.linalg.norm((c - hands[RIGHT, :3, 3])[:2])) for c in self.doors)
            if near < self.reach:
                self.pressed_at = k
        if self.pressed_at is not None and k - self.pressed_at < 5:
            buttons[RIGHT] = BUTTON_TRIGGER
        return head, hands, np.ones(2, bool), buttons


class HeadlessBackend:
    """Frames from a trajectory (callable (k, t) -> head, hands, hands_valid, buttons) or a :class:`Recording`."""

    name = "headless"

    def __init__(self, trajectory=None, target_hz: float = 90.0, width: int = 512, height: int = 512,
                 realtime: bool = False, yfov_deg: float = 100.0):
        if not (1 <= target_hz <= 1000):
            raise ConfigError(f"target frame rate must be 1-1000 Hz, got {target_hz}")
        self.trajectory, self.target_hz, self.realtime = trajectory, float(target_hz), realtime
        self.width, self.height, self.yfov_deg = width, height, yfov_deg
        self.recording = trajectory if isinstance(trajectory, Recording) else None
        if self.recording is not None:
            self.target_hz = float(self.recording.meta.get("target_hz", target_hz))
        from app.scene.eyes import default_eyes

        self.eye_to_head, self.projections = default_eyes(width, height, yfov_deg)
        self.k = 0
        self.submitted = 0
        self._t0 = None

    def begin(self, session) -> None:
        if self.trajectory is None:
            self.trajectory = session.default_trajectory(self.target_hz)

    def wait_frame(self) -> FrameInput:
        k = self.k
        self.k += 1
        if self.recording is not None:
            if k >= len(self.recording.frames):
                f = self.recording.frames[-1]
                return FrameInput(k, f.t, f.dt, f.head, f.hands, f.hands_valid, np.zeros(2, np.uint64), quit=True)
            return self.recording.frames[k]
        dt = 1.0 / self.target_hz
        if self.realtime:  # pace to the wall clock (fixed-step simulation time either way)
            now = time.perf_counter()
            if self._t0 is None:
                self._t0 = now
            wait = self._t0 + k * dt - now
            if wait > 0:
                time.sleep(wait)
        head, hands, valid, buttons = self.trajectory(k, k * dt)
        return FrameInput(k, k * dt, dt, head, hands, valid, buttons)

    def submit(self, views) -> None:
        self.submitted += 1

    def close(self) -> None:
        pass
