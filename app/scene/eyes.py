"""Eye geometry for backends that have no headset to ask (desktop, headless): eye -> head offsets at the
interpupillary distance and a symmetric projection per eye. Numpy only (no renderer import)."""
from __future__ import annotations

import numpy as np

IPD = 0.064  # m between the eyes (adult average)


def eye_offsets(ipd: float = IPD) -> np.ndarray:
    """(2, 4, 4) eye -> head transforms: left eye at -ipd/2 along the head's x (right) axis, right eye at +ipd/2."""
    e = np.tile(np.eye(4), (2, 1, 1))
    e[0, 0, 3], e[1, 0, 3] = -0.5 * ipd, 0.5 * ipd
    return e


def default_eyes(width: int, height: int, yfov_deg: float = 100.0, ipd: float = IPD, znear: float = 0.05,
                 zfar: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
    """(eye_to_head (2, 4, 4), projections (2, 4, 4))."""
    from app.vr.transforms import projection

    p = projection(yfov_deg, width / height, znear, zfar)
    return eye_offsets(ipd), np.stack([p, p])
