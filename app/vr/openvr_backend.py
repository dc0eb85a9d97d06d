"""The OpenVR backend (pyopenvr): a scene application whose loop is paced by ``IVRCompositor.waitGetPoses``.

Per frame: wait for the poses (this blocks until the compositor's "running start" before the next refresh, which
is what frame-locks the loop), turn the headset and controller poses into world poses (:mod:`app.vr.transforms`),
read the controllers' buttons, and after rendering upload each eye into an OpenGL texture (in the renderer's current
context) and submit it. Per-eye projections and eye -> head transforms come from the runtime, as does the refresh
rate and the recommended render size.
"""
from __future__ import annotations

import contextlib
import os
import sys

import time

import numpy as np

from app.vr.frame import LEFT, RIGHT, FrameInput
from app.vr.transforms import hmd34, hmd44, origin_matrix, tracked_to_world
from sonicverse_core.errors import DependencyError, DeviceError

HOW = "use --backend desktop (a window with mouse and keyboard) or --backend headless (no display)"


def why_not(exc) -> str:
    """One line saying why OpenVR did not start, from pyopenvr's InitError class."""
    name = type(exc).__name__
    if "PathRegistryNotFound" in name or "InstallationNotFound" in name or "VRClientDLLNotFound" in name:
        why = "no OpenVR runtime (SteamVR) is installed"
    elif "HmdNotFound" in name:
        why = "no VR headset is connected"
    elif "NoServerForBackgroundApp" in name or "ServerNotFound" in name or "Init_IPCFailed" in name:
        why = "the OpenVR runtime (SteamVR) is not running"
    else:
        why = f"the OpenVR runtime refused to start ({name})"
    return f"OpenVR did not start: {why}; {HOW}"


@contextlib.contextmanager
def runtime_chatter(keep: list):
    """Hold what OpenVR's client library prints straight to file descriptor 2 (its complaint about a missing
    runtime, before our one-line error); the text is appended to ``keep`` for the caller to show when it wants."""
    import tempfile

    saved = os.dup(2)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            keep.append(tmp.read().decode(errors="replace"))


class OpenVRBackend:
    name = "openvr"

    def __init__(self, size: tuple | None = None, znear: float = 0.05, zfar: float = 50.0):
        try:
            import openvr
        except ImportError as exc:
            raise DependencyError(f"the OpenVR backend needs pyopenvr (pip install -r requirements.txt): {exc}") \
                from None
        self.vr = openvr
        said: list[str] = []
        try:
            with runtime_chatter(said):
                self.system = openvr.init(openvr.VRApplication_Scene)
        except openvr.error_code.InitError as exc:
            raise DeviceError(why_not(exc)) from None
        except OSError as exc:  # the runtime's client library failed to load
            raise DeviceError(f"OpenVR did not start: {exc}; {HOW}") from None
        if said and said[0].strip():  # it started: what the runtime said is worth showing
            sys.stderr.write(said[0])
        self.compositor = openvr.VRCompositor()
        if size is None:
            size = self.system.getRecommendedRenderTargetSize()
        self.width, self.height = int(size[0]), int(size[1])
        try:
            hz = float(self.system.getFloatTrackedDeviceProperty(openvr.k_unTrackedDeviceIndex_Hmd,
                                                                 openvr.Prop_DisplayFrequency_Float))
        except openvr.error_code.TrackedPropertyError:
            hz = 0.0
        self.target_hz = hz if hz > 1 else 90.0
        eyes = (openvr.Eye_Left, openvr.Eye_Right)
        self.eye_to_head = np.stack([hmd34(self.system.getEyeToHeadTransform(e)) for e in eyes])
        self.projections = np.stack([hmd44(self.system.getProjectionMatrix(e, znear, zfar)) for e in eyes])
        self.poses = (openvr.TrackedDevicePose_t * openvr.k_unMaxTrackedDeviceCount)()
        self.origin = np.eye(4)
        self.head = np.eye(4)
        self.hands = np.tile(np.eye(4), (2, 1, 1))
        self.textures = None
        self.bounds = openvr.VRTextureBounds_t(0.0, 1.0, 1.0, 0.0)  # rows come top first: flip v
        self.k, self._t, self._last, self.submits = 0, 0.0, None, 0

    def begin(self, session) -> None:
        """The play area's floor centre is put at the session's spawn point, facing +x."""
        self.origin = origin_matrix(session.spawn[0], session.spawn[1], session.scene.floor_z, 0.0)

    def wait_frame(self) -> FrameInput:
        vr = self.vr
        self.compositor.waitGetPoses(self.poses, None)
        now = time.perf_counter()
        period = 1.0 / self.target_hz
        dt = period if self._last is None else max(1, round((now - self._last) / period)) * period
        self._last = now
        hmd = self.poses[vr.k_unTrackedDeviceIndex_Hmd]
        if hmd.bPoseIsValid:  # a lost tracking frame keeps the last head pose
            self.head = tracked_to_world(self.origin, hmd34(hmd.mDeviceToAbsoluteTracking))
        valid = np.zeros(2, bool)
        buttons = np.zeros(2, np.uint64)
        for i in range(1, vr.k_unMaxTrackedDeviceCount):
            if self.system.getTrackedDeviceClass(i) != vr.TrackedDeviceClass_Controller:
                continue
            role = self.system.getControllerRoleForTrackedDeviceIndex(i)
            k = LEFT if role == vr.TrackedControllerRole_LeftHand else RIGHT if \
                role == vr.TrackedControllerRole_RightHand else None
            if k is None:
                continue
            p = self.poses[i]
            if p.bPoseIsValid:
                self.hands[k] = tracked_to_world(self.origin, hmd34(p.mDeviceToAbsoluteTracking))
                valid[k] = True
            ok, state = self.system.getControllerState(i)
            if ok:
                buttons[k] = np.uint64(state.ulButtonPressed)
        k = self.k
        self.k += 1
        self._t = 0.0 if k == 0 else self._t + dt
        return FrameInput(k, self._t, dt, self.head.copy(), self.hands.copy(), valid, buttons)

    def _make_textures(self) -> None:
        from OpenGL import GL

        self.textures = [int(t) for t in np.atleast_1d(GL.glGenTextures(2))]
        for t in self.textures:
            GL.glBindTexture(GL.GL_TEXTURE_2D, t)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_LINEAR)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAG_FILTER, GL.GL_LINEAR)
            GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAX_LEVEL, 0)
            GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, GL.GL_RGBA8, self.width, self.height, 0, GL.GL_RGB,
                            GL.GL_UNSIGNED_BYTE, None)

    def submit(self, views) -> None:
        """Upload both eyes ((2, H, W, 3) uint8, the renderer's GL context current) and submit them."""
        if views is None:  # audio-only: nothing to show; the compositor keeps pacing
            return
        from OpenGL import GL

        vr = self.vr
        if self.textures is None:
            self._make_textures()
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        for eye, tex, img in zip((vr.Eye_Left, vr.Eye_Right), self.textures, views):
            GL.glBindTexture(GL.GL_TEXTURE_2D, tex)
            GL.glTexSubImage2D(GL.GL_TEXTURE_2D, 0, 0, 0, self.width, self.height, GL.GL_RGB, GL.GL_UNSIGNED_BYTE,
                               np.ascontiguousarray(img))
            t = vr.Texture_t()
            t.handle, t.eType, t.eColorSpace = tex, vr.TextureType_OpenGL, vr.ColorSpace_Gamma
            self.compositor.submit(eye, t, self.bounds)
        GL.glFlush()  # let the driver start (OpenVR's advice for GL apps)
        self.submits += 1

    def close(self) -> None:
        if self.textures is not None:
            try:
                from OpenGL import GL

                GL.glDeleteTextures(self.textures)
            except Exception:  # noqa: BLE001 - the context may be gone already
                pass
            self.textures = None
        self.vr.shutdown()
