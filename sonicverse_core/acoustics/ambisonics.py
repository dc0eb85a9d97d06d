"""Real spherical harmonics (ACN order, N3D normalisation: the mean of Y^2 over the sphere is 1), orders 0-2."""
from __future__ import annotations

import numpy as np

from sonicverse_core.errors import ConfigError


def real_sh(directions: np.ndarray, order: int) -> np.ndarray:
    """Unit vectors (m, 3) (x fwd, y left, z up) -> (m, (order + 1)^2) float64."""
    if order not in (0, 1, 2):
        raise ConfigError(f"ambisonic order must be 0, 1 or 2, got {order}")
    d = np.atleast_2d(np.asarray(directions, np.float64))
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    cols = [np.ones_like(x)]
    if order >= 1:
        s3 = np.sqrt(3.0)
        cols += [s3 * y, s3 * z, s3 * x]
    if order >= 2:
        s15 = np.sqrt(15.0)
        cols += [s15 * x * y, s15 * y * z, np.sqrt(5.0) / 2 * (3 * z * z - 1), s15 * x * z, s15 / 2 * (x * x - y * y)]
    return np.stack(cols, axis=1)
