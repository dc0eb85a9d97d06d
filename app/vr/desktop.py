"""The desktop backend: a PyQt6 window showing both eyes side by side (or one), head pose from mouse and keyboard,
paced by a frame clock at the display's refresh rate.

Keys: W/S forward/back, A/D sideways, arrow keys or dragging with the left mouse button look around, E the right
trigger (opens/closes a door within reach of the right hand), G the grip, Esc or closing the window quits. The hands
are held in front of the body as in the headless backend. The input becomes the same :class:`FrameInput` as a
headset's, so tasks and recordings do not know which backend ran.
"""
from __future__ import annotations

import math
import os
import sys
import time

import numpy as np

from app.vr.frame import BUTTON_GRIP, BUTTON_TRIGGER, RIGHT, FrameInput
from app.vr.headless import EYE_HEIGHT, WALK_SPEED, hand_poses
from app.vr.transforms import look_matrix
from sonicverse_core.errors import DependencyError, DeviceError

TURN_SPEED = 90.0  # deg/s with the arrow keys
MOUSE_DEG_PER_PX = 0.25


def _qt():
    try:
        from PyQt6 import QtCore, QtGui, QtWidgets
    except ImportError as exc:
        raise DependencyError(f"the desktop backend needs PyQt6 (pip install -r requirements.txt): {exc}") from None
    return QtCore, QtGui, QtWidgets


class DesktopBackend:
    name = "desktop"

    def __init__(self, width: int = 512, height: int = 512, target_hz: float | None = None, eyes: int = 2,
                 yfov_deg: float = 100.0, start: tuple | None = None):
        QtCore, QtGui, QtWidgets = _qt()
        self.QtCore, self.QtGui = QtCore, QtGui
        self.app = QtWidgets.QApplication.instance()
        if self.app is None:
            if sys.platform.startswith("linux") and not any(
                    os.environ.get(k) for k in ("DISPLAY", "WAYLAND_DISPLAY", "QT_QPA_PLATFORM")):
                # Qt would abort the whole process (qFatal), not raise
                raise DeviceError("no display for the desktop backend (neither DISPLAY nor WAYLAND_DISPLAY is set); "
                                  "run it in a desktop session or under xvfb-run, or use --backend headless")
            self.app = QtWidgets.QApplication(["sonicverse"])
        from app.scene.eyes import default_eyes

        self.width, self.height, self.n_eyes = width, height, eyes
        self.eye_to_head, self.projections = default_eyes(width, height, yfov_deg)
        screen = self.app.primaryScreen()
        rate = screen.refreshRate() if screen is not None else 0.0
        self.target_hz = float(target_hz or (rate if rate and rate > 1 else 60.0))
        self.window = _make_window(QtWidgets, QtGui, QtCore, self, width * eyes, height)
        self.window.setWindowTitle("Sonicverse")
        self.window.resize(width * eyes, height)
        self.window.show()
        self.keys: set = set()
        self.drag = np.zeros(2)
        self.pose = np.array(start if start is not None else (0.0, 0.0, EYE_HEIGHT, 0.0, 0.0), float)
        self.image = None
        self.k, self._next, self.closed = 0, None, False

    def begin(self, session) -> None:
        self.pose[:3] = (session.spawn[0], session.spawn[1], session.scene.floor_z + EYE_HEIGHT)

    # --- input ----------------------------------------------------------------------------------------------------
    def _advance(self, dt: float) -> None:
        K = self.QtCore.Qt.Key
        k = self.keys
        turn = (K.Key_Left in k) - (K.Key_Right in k)
        tilt = (K.Key_Up in k) - (K.Key_Down in k)
        self.pose[3] = (self.pose[3] + TURN_SPEED * dt * turn - MOUSE_DEG_PER_PX * self.drag[0] + 180) % 360 - 180
        self.pose[4] = float(np.clip(self.pose[4] + TURN_SPEED * dt * tilt - MOUSE_DEG_PER_PX * self.drag[1],
                                     -80, 80))
        self.drag[:] = 0
        fwd = (K.Key_W in k) - (K.Key_S in k)
        side = (K.Key_A in k) - (K.Key_D in k)
        a = math.radians(self.pose[3])
        self.pose[0] += WALK_SPEED * dt * (fwd * math.cos(a) - side * math.sin(a))
        self.pose[1] += WALK_SPEED * dt * (fwd * math.sin(a) + side * math.cos(a))

    def wait_frame(self) -> FrameInput:
        period = 1.0 / self.target_hz
        now = time.perf_counter()
        if self._next is None:
            self._next = now
        if self._next > now:
            time.sleep(self._next - now)
        now = time.perf_counter()
        late = max(0, int((now - self._next) / period))  # refreshes missed: the clock skips them
        steps = 1 + late
        self._next += steps * period
        self.app.processEvents()
        dt = steps * period
        self._advance(dt)
        head = look_matrix(*self.pose)
        K = self.QtCore.Qt.Key
        buttons = np.zeros(2, np.uint64)
        if K.Key_E in self.keys:
            buttons[RIGHT] |= np.uint64(BUTTON_TRIGGER)
        if K.Key_G in self.keys:
            buttons[RIGHT] |= np.uint64(BUTTON_GRIP)
        k = self.k
        self.k += 1
        t = k * period if k == 0 else self._t + dt
        self._t = t
        return FrameInput(k, t, dt, head, hand_poses(head), np.ones(2, bool), buttons,
                          quit=self.closed or K.Key_Escape in self.keys)

    # --- output ---------------------------------------------------------------------------------------------------
    def submit(self, views) -> None:
        if views is None:  # audio-only: a black window that still takes the keys
            img = np.zeros((self.height, self.width * self.n_eyes, 3), np.uint8)
        else:
            img = np.ascontiguousarray(np.concatenate(list(views[:self.n_eyes]), axis=1))
        self.image = img
        h, w = img.shape[:2]
        self._qimage = self.QtGui.QImage(img.data, w, h, 3 * w, self.QtGui.QImage.Format.Format_RGB888)
        self.window.update()
        self.app.processEvents()

    def screenshot(self) -> np.ndarray:
        """(H, W, 3) uint8 of what the window shows now (Qt's own grab of the widget)."""
        self.window.repaint()
        im = self.window.grab().toImage().convertToFormat(self.QtGui.QImage.Format.Format_RGB888)
        ptr = im.constBits()
        ptr.setsize(im.sizeInBytes())
        a = np.frombuffer(ptr, np.uint8).reshape(im.height(), im.bytesPerLine())
        return a[:, :3 * im.width()].reshape(im.height(), im.width(), 3).copy()

    def close(self) -> None:
        self.window.close()
        self.app.processEvents()


def _make_window(QtWidgets, QtGui, QtCore, backend, w, h):
    class View(QtWidgets.QWidget):
        def __init__(self):
            super().__init__()
            self.setFocusPolicy(QtCore.Qt.FocusPolicy.StrongFocus)
            self.setMinimumSize(w // 4, h // 4)
            self._last = None

        def paintEvent(self, event):
            p = QtGui.QPainter(self)
            img = getattr(backend, "_qimage", None)
            if img is not None:
                p.drawImage(self.rect(), img)
            else:
                p.fillRect(self.rect(), QtGui.QColor(0, 0, 0))
            p.end()

        def keyPressEvent(self, e):
            if not e.isAutoRepeat():
                backend.keys.add(QtCore.Qt.Key(e.key()))

        def keyReleaseEvent(self, e):
            if not e.isAutoRepeat():
                backend.keys.discard(QtCore.Qt.Key(e.key()))

        def mousePressEvent(self, e):
            self._last = e.position()

        def mouseMoveEvent(self, e):
            if self._last is not None:
                d = e.position() - self._last
                backend.drag += (d.x(), d.y())
                self._last = e.position()

        def mouseReleaseEvent(self, e):
            self._last = None

        def closeEvent(self, e):
            backend.closed = True
            e.accept()

    return View()
