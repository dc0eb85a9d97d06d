"""A TurtleBot-2-like differential-drive robot (Kobuki base).

Numbers from the Kobuki base of the TurtleBot 2: wheel separation 0.230 m, wheel radius 0.035 m, top speed
0.7 m/s, rotation limited to 180 deg/s by the firmware, base diameter 0.354 m. The action is the two wheel
velocities normalised to [-1, 1] (1 = the wheel's rim at top speed). Integration is exact along the arc of each
sub-step; sub-steps are short enough (``substep`` metres of travel at most) that the robot never tunnels through a
wall thinner than a navigation cell.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sonicverse_core.errors import ActionError, ConfigError


@dataclass(frozen=True)
class RobotConfig:
    wheel_base: float = 0.230  # m between the wheels
    wheel_radius: float = 0.035  # m
    max_speed: float = 0.7  # m/s at the wheel rim (= the robot's top linear speed)
    max_turn_deg: float = 180.0  # deg/s: the Kobuki firmware's limit
    radius: float = 0.177  # m, half the base diameter
    height: float = 0.42  # m: the top plate, where carried objects ride
    camera_height: float = 0.55  # m: depth camera on the top plate (Kinect/Astra mount)
    ear_height: float = 0.55  # m: microphones next to the camera
    ear_spacing: float = 0.18  # m between the two microphones (the renderer uses its HRTF's head)
    substep: float = 0.02  # m of travel per integration sub-step at most
    collision: str = "slide"  # slide | stop

    def __post_init__(self):
        for name in ("wheel_base", "wheel_radius", "max_speed", "max_turn_deg", "radius", "substep"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"robot {name} must be a positive number, got {v}")
        if self.collision not in ("slide", "stop"):
            raise ConfigError(f"robot collision must be 'slide' or 'stop', got '{self.collision}'")

    @property
    def max_wheel_omega(self) -> float:
        """rad/s of a wheel at action 1."""
        return self.max_speed / self.wheel_radius


def wheel_action(action, n: int = 2) -> np.ndarray:
    """Validate an action: ``n`` finite numbers. Values outside [-1, 1] are clipped (documented; a motor cannot
    go faster than its top speed); NaN, infinities or a wrong shape raise :class:`ActionError`."""
    try:
        a = np.asarray(action, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ActionError(f"action must be {n} numbers, got {action!r}") from None
    if a.shape != (n,):
        raise ActionError(f"action must be {n} numbers, got shape {np.shape(action)}")
    if not np.all(np.isfinite(a)):
        raise ActionError(f"action must be finite, got {a.tolist()}")
    return np.clip(a, -1.0, 1.0)


def body_velocity(cfg: RobotConfig, wheels: np.ndarray) -> tuple[float, float]:
    """(v m/s, omega rad/s) for normalised wheel velocities (left, right)."""
    vl, vr = float(wheels[0]) * cfg.max_speed, float(wheels[1]) * cfg.max_speed
    v = 0.5 * (vl + vr)
    w = (vr - vl) / cfg.wheel_base
    wmax = math.radians(cfg.max_turn_deg)
    return v, min(max(w, -wmax), wmax)


def integrate(cfg: RobotConfig, pose: np.ndarray, wheels: np.ndarray, dt: float, free) -> tuple[np.ndarray, bool, float]:
    """Advance pose (x, y, yaw_deg) by ``dt`` s; ``free(x, y) -> bool`` says where the robot's centre may be.

    Collision ("slide"): a sub-step that would end in a blocked place keeps whichever of its x-only or y-only
    components is free (the robot slides along walls, exactly so along the axis-aligned walls of the built-in
    homes); if neither is, the robot stops there. ("stop"): the sub-step is dropped. Rotation is never blocked (a
    round base turns in place). Returns the new pose, whether it bumped, and the distance travelled.
    """
    v, w = body_velocity(cfg, wheels)
    x, y, yaw = float(pose[0]), float(pose[1]), math.radians(float(pose[2]))
    n = max(1, int(math.ceil(abs(v) * dt / cfg.substep)))
    h = dt / n
    bumped, travelled = False, 0.0
    for _ in range(n):
        if abs(w) > 1e-9:
            r = v / w
            dx = r * (math.sin(yaw + w * h) - math.sin(yaw))
            dy = -r * (math.cos(yaw + w * h) - math.cos(yaw))
        else:
            dx, dy = v * h * math.cos(yaw), v * h * math.sin(yaw)
        yaw += w * h
        if dx == 0.0 and dy == 0.0:
            continue
        if free(x + dx, y + dy):
            x, y = x + dx, y + dy
            travelled += math.hypot(dx, dy)
            continue
        bumped = True
        if cfg.collision == "slide":
            ox, oy = free(x + dx, y), free(x, y + dy)
            if ox and (not oy or abs(dx) >= abs(dy)):
                x += dx
                travelled += abs(dx)
            elif oy:
                y += dy
                travelled += abs(dy)
    yaw_deg = (math.degrees(yaw) + 180.0) % 360.0 - 180.0
    return np.array([x, y, yaw_deg]), bumped, travelled
