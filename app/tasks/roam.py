"""Frame tasks: the code a VR session runs once per frame, the same under every backend.

A task gets the session (its world, scene, audio) and the frame's input, and changes the world: that is the whole
contract, so a task written against the headless backend runs unchanged in a headset. :class:`FreeRoam` is the
default: the user walks around; the right trigger opens or closes the nearest door within reach of the right hand;
a robot keeps company (turns towards the user and follows at 1-2 m, stopping at walls).
"""
from __future__ import annotations

import math

import numpy as np

from app.vr.frame import BUTTON_TRIGGER, RIGHT, FrameInput

REACH = 1.0  # m from the hand to a door's leaf centre


class FrameTask:
    name = "task"

    def reset(self, session) -> None:
        """Called once before the first frame."""

    def step(self, session, frame: FrameInput) -> None:
        """One simulation step of ``frame.dt`` seconds."""

    def summary(self) -> dict:
        return {}


class FreeRoam(FrameTask):
    name = "free-roam"

    def __init__(self, follow: bool = True, near: float = 1.2, far: float = 2.0):
        self.follow, self.near, self.far = follow, near, far
        self.door_toggles: list[tuple[int, str, float]] = []
        self.refused: list[str] = []
        self._trigger = False

    def reset(self, session) -> None:
        self._trigger = False

    def step(self, session, f: FrameInput) -> None:
        down = f.pressed(RIGHT, BUTTON_TRIGGER)
        if down and not self._trigger and f.hands_valid[RIGHT]:
            self._toggle_door(session, f)
        self._trigger = down
        if self.follow and session.world is not None:
            self._follow(session.world, f)

    def _toggle_door(self, session, f: FrameInput) -> None:
        from sonicverse_core.errors import ActionError

        hand = f.hands[RIGHT][:3, 3]
        best, dist = None, REACH
        for d in session.scene.doors:
            c = d.world_bounds(d.pose).mean(axis=0)
            r = float(np.linalg.norm((c - hand)[:2]))
            if r < dist:
                best, dist = d, r
        if best is None:
            return
        target = 0.0 if best.is_open else 1.0
        try:
            if session.world is not None:
                session.world.set_door(best.name, target)
            else:
                session.scene.set_door(best.name, target)
            self.door_toggles.append((f.index, best.name, target))
        except ActionError as exc:  # the robot stands in the leaf's way: the door stays, the session goes on
            self.refused.append(str(exc))
            session.events.append(str(exc))

    def _follow(self, world, f: FrameInput) -> None:
        x, y, yaw = world.pose
        hx, hy = f.head[0, 3], f.head[1, 3]
        d = math.hypot(hx - x, hy - y)
        err = (math.degrees(math.atan2(hy - y, hx - x)) - yaw + 180.0) % 360.0 - 180.0
        turn = float(np.clip(err / 60.0, -1.0, 1.0))
        fwd = 0.0 if abs(err) > 45 or d < self.near else float(np.clip((d - self.near) / (self.far - self.near),
                                                                       0.0, 1.0))
        world.drive((np.clip(fwd - 0.5 * turn, -1, 1), np.clip(fwd + 0.5 * turn, -1, 1)), f.dt)

    def summary(self) -> dict:
        return {"door_toggles": len(self.door_toggles), "doors_refused": len(self.refused)}
