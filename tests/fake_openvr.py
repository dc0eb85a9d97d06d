"""Fakes of OpenVR's IVRSystem and IVRCompositor built from pyopenvr's real types (no runtime can exist here).

They are pyopenvr's own ``IVRSystem`` / ``IVRCompositor`` wrapper classes over a function table of the real
``*_FnTable`` ctypes structure whose entries are ctypes callbacks: calls go through pyopenvr's real marshalling
(``byref`` of poses, textures and bounds, error codes checked by its error classes). The two entries that return a
structure by value (ctypes callbacks cannot) are overridden in Python and return real ``HmdMatrix44_t`` /
``HmdMatrix34_t``. A headset with two controllers (indices 1: left, 2: right) follows a scripted path.
"""
from __future__ import annotations

import ctypes

import numpy as np
import openvr

from app.vr.transforms import fill_hmd34

RATE = 90.0
SIZE = (160, 144)
IPD = 0.066


def _set(table, name, fn):
    setattr(table, name, type(getattr(table, name))(fn))
    return getattr(table, name)


class FakeSystem(openvr.IVRSystem):
    def __init__(self, rig):
        self.rig = rig
        self.function_table = t = openvr.IVRSystem_FnTable()
        self._keep = []

        def size(w, h):
            w[0], h[0] = SIZE
        self._keep.append(_set(t, "getRecommendedRenderTargetSize", size))
        self._keep.append(_set(t, "getTrackedDeviceClass", lambda i: {
            0: openvr.TrackedDeviceClass_HMD, 1: openvr.TrackedDeviceClass_Controller,
            2: openvr.TrackedDeviceClass_Controller}.get(i, openvr.TrackedDeviceClass_Invalid)))
        self._keep.append(_set(t, "getControllerRoleForTrackedDeviceIndex", lambda i: {
            1: openvr.TrackedControllerRole_LeftHand, 2: openvr.TrackedControllerRole_RightHand}.get(i, 0)))

        def prop(i, p, err):
            err[0] = 0
            return RATE if (i, p) == (0, openvr.Prop_DisplayFrequency_Float) else 0.0
        self._keep.append(_set(t, "getFloatTrackedDeviceProperty", prop))

        def state(i, st, size):
            assert size == ctypes.sizeof(openvr.VRControllerState_t)
            st[0].unPacketNum = rig.frame
            st[0].ulButtonPressed = rig.buttons.get((rig.frame, i), 0)
            return 1
        self._keep.append(_set(t, "getControllerState", state))

    def getProjectionMatrix(self, eye, nearZ, farZ):
        m = openvr.HmdMatrix44_t()
        # an asymmetric frustum per eye (the inner side narrower), as real lenses give
        l, r, b, tp = (-1.2, 1.0, -1.1, 1.1) if eye == openvr.Eye_Left else (-1.0, 1.2, -1.1, 1.1)
        p = np.zeros((4, 4), np.float32)
        p[0, 0], p[0, 2] = 2 / (r - l), (r + l) / (r - l)
        p[1, 1], p[1, 2] = 2 / (tp - b), (tp + b) / (tp - b)
        p[2, 2], p[2, 3] = -(farZ + nearZ) / (farZ - nearZ), -2 * farZ * nearZ / (farZ - nearZ)
        p[3, 2] = -1
        np.ctypeslib.as_array(m.m)[:] = p
        self.rig.projection_calls.append((int(eye), nearZ, farZ))
        return m

    def getEyeToHeadTransform(self, eye):
        m = openvr.HmdMatrix34_t()
        e = np.eye(4)
        e[0, 3] = -IPD / 2 if eye == openvr.Eye_Left else IPD / 2
        fill_hmd34(m, e)
        return m


class FakeCompositor(openvr.IVRCompositor):
    def __init__(self, rig):
        self.rig = rig
        self.function_table = t = openvr.IVRCompositor_FnTable()
        self._keep = []

        def wait(render, n_render, game, n_game):
            assert n_render == openvr.k_unMaxTrackedDeviceCount and n_game == 0
            rig.frame += 1
            rig.submitted_this_frame = set()
            for i, m in ((0, rig.hmd(rig.frame)), (1, rig.hand(rig.frame, 0)), (2, rig.hand(rig.frame, 1))):
                fill_hmd34(render[i].mDeviceToAbsoluteTracking, m)
                render[i].bPoseIsValid = not (i == 0 and rig.frame in rig.lost)
                render[i].bDeviceIsConnected = True
                render[i].eTrackingResult = openvr.TrackingResult_Running_OK
            return 0
        self._keep.append(_set(t, "waitGetPoses", wait))

        def submit(eye, tex, bounds, flags):
            eye = int(eye)
            if eye in rig.submitted_this_frame:
                return int(openvr.VRCompositorError_AlreadySubmitted)  # pyopenvr raises it
            rig.submitted_this_frame.add(eye)
            rig.submits.append({"frame": rig.frame, "eye": eye, "handle": tex[0].handle, "type": int(tex[0].eType),
                                "colorspace": int(tex[0].eColorSpace),
                                "bounds": (bounds[0].uMin, bounds[0].vMin, bounds[0].uMax, bounds[0].vMax),
                                "pixels": rig.read_texture(tex[0].handle) if tex[0].handle else None})
            return 0
        self._keep.append(_set(t, "submit", submit))


class Rig:
    """The scripted headset: the head at 1.7 m in the play area turning 1 deg per frame; hands in front."""

    def __init__(self):
        self.frame = 0
        self.buttons: dict = {}  # (frame, device index) -> mask
        self.lost: set = set()  # frames whose HMD pose is invalid
        self.submits: list = []
        self.projection_calls: list = []
        self.submitted_this_frame: set = set()
        self.shutdowns = 0

    def hmd(self, k: int) -> np.ndarray:
        a = np.radians(k)  # about the tracking y axis (up)
        m = np.eye(4)
        m[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
        m[:3, 3] = (0.1 * np.sin(a), 1.7, -0.01 * k)
        return m

    def hand(self, k: int, side: int) -> np.ndarray:
        m = np.eye(4)
        m[:3, 3] = (-0.2 if side == 0 else 0.2, 1.1, -0.4)
        return m

    @staticmethod
    def read_texture(handle: int):
        from OpenGL import GL

        GL.glBindTexture(GL.GL_TEXTURE_2D, int(handle))
        w = GL.glGetTexLevelParameteriv(GL.GL_TEXTURE_2D, 0, GL.GL_TEXTURE_WIDTH)
        h = GL.glGetTexLevelParameteriv(GL.GL_TEXTURE_2D, 0, GL.GL_TEXTURE_HEIGHT)
        GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
        raw = GL.glGetTexImage(GL.GL_TEXTURE_2D, 0, GL.GL_RGB, GL.GL_UNSIGNED_BYTE)
        return np.frombuffer(raw, np.uint8).reshape(int(h), int(w), 3).copy()


def install(monkeypatch) -> Rig:
    """Route openvr.init / VRCompositor / shutdown to the fakes; returns the rig that records what happened."""
    rig = Rig()
    system = FakeSystem(rig)
    comp = FakeCompositor(rig)

    def init(app_type, info=None):
        assert app_type == openvr.VRApplication_Scene
        return system

    def shutdown():
        rig.shutdowns += 1

    monkeypatch.setattr(openvr, "init", init)
    monkeypatch.setattr(openvr, "VRCompositor", lambda: comp)
    monkeypatch.setattr(openvr, "shutdown", shutdown)
    return rig
