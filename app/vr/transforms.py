"""OpenVR <-> Sonicverse coordinates, written once.

Sonicverse: z up, x forward at yaw 0, left ear towards +y. OpenVR's tracking space (and its head and eye frames):
x right, y up, -z forward (``HmdMatrix34_t``'s docstring). A point's coordinates therefore map as
``sv = (-vr_z, -vr_x, vr_y)``: :data:`SV_FROM_VR`. A tracked pose ``T`` (device -> tracking, 3x4) becomes the 4x4
device -> world pose ``origin @ SV_FROM_VR @ T``, where ``origin`` places the play area in the scene (a position and
a yaw). The head's frame is then an OpenGL camera frame (x right, y up, looking along -z), which is what pyrender
wants for a camera pose, and the eye poses are ``head @ eye_to_head``.
"""
from __future__ import annotations

import math

import numpy as np

from sonicverse_core.errors import PoseError
# the play area's floor centre placed in the scene: a position and a yaw about z
from sonicverse_core.scene.model import yaw_pose as origin_matrix  # noqa: F401
from sonicverse_core.sensors.camera import camera_matrix as look_matrix  # noqa: F401  (numpy only; no GL import)

SV_FROM_VR = np.array([[0.0, 0.0, -1.0, 0.0],
                       [-1.0, 0.0, 0.0, 0.0],
                       [0.0, 1.0, 0.0, 0.0],
                       [0.0, 0.0, 0.0, 1.0]])


def hmd34(m) -> np.ndarray:
    """4x4 float64 from an OpenVR ``HmdMatrix34_t`` (rows of 4)."""
    out = np.eye(4)
    out[:3, :] = np.ctypeslib.as_array(m.m)
    return out


def hmd44(m) -> np.ndarray:
    """4x4 float64 from an OpenVR ``HmdMatrix44_t``."""
    return np.ctypeslib.as_array(m.m).astype(np.float64)


def fill_hmd34(dst, m: np.ndarray) -> None:
    """Write the top 3 rows of a 4x4 into an ``HmdMatrix34_t`` (used by the fakes and tests)."""
    np.ctypeslib.as_array(dst.m)[:] = np.asarray(m, np.float32)[:3, :]


def tracked_to_world(origin: np.ndarray, tracked: np.ndarray) -> np.ndarray:
    """Device -> world (z up) from device -> OpenVR tracking space."""
    return origin @ SV_FROM_VR @ tracked


def world_to_tracked(origin: np.ndarray, world: np.ndarray) -> np.ndarray:
    return np.linalg.inv(SV_FROM_VR) @ np.linalg.inv(origin) @ world


def head_pose(m: np.ndarray) -> tuple:
    """(x, y, z, yaw, pitch) in metres / degrees of a head (camera-frame) pose; roll is dropped (the listener model
    has none). Raises PoseError for a matrix that is not finite."""
    if not np.all(np.isfinite(m)):
        raise PoseError("head pose is not finite (NaN or infinity)")
    fwd = -m[:3, 2]
    n = float(np.linalg.norm(fwd))
    if not 0.5 < n < 2.0:
        raise PoseError(f"head pose is not a rotation (forward axis of length {n:.3f})")
    fwd = fwd / n
    return (float(m[0, 3]), float(m[1, 3]), float(m[2, 3]), math.degrees(math.atan2(fwd[1], fwd[0])),
            math.degrees(math.asin(min(max(fwd[2], -1.0), 1.0))))


def projection(fov_y_deg: float, aspect: float, znear: float, zfar: float) -> np.ndarray:
    """Symmetric OpenGL perspective projection (what a desktop or headless eye uses; OpenVR gives its own)."""
    f = 1.0 / math.tan(math.radians(fov_y_deg) / 2)
    p = np.zeros((4, 4))
    p[0, 0], p[1, 1] = f / aspect, f
    p[2, 2], p[2, 3] = (zfar + znear) / (znear - zfar), 2 * zfar * znear / (znear - zfar)
    p[3, 2] = -1.0
    return p
