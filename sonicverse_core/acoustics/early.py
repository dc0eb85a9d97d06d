"""Early reflections: image sources of a probe's proxy box (Allen & Berkley 1979).

For a box [lo, hi] and a source inside it, the image positions along each axis are x' = (1 - 2q) x + 2 m L
(box-local coordinates, q in {0, 1}, m integer); such an image has reflected |m - q| times off the low wall and
|m| times off the high wall of that axis. All images up to a reflection ``order`` are enumerated once per order
(the lattice); ``kernels.image_taps`` places them for every source each block. A wall reflects sqrt(1 - alpha) of the
amplitude, alpha its material's mean absorption over 500 Hz - 2 kHz; an open side (no surface within reach of the
probe) reflects nothing.
"""
from __future__ import annotations

import itertools
from functools import lru_cache

import numpy as np

from sonicverse_core.scene.materials import BANDS, get_material

MID_BANDS = (BANDS >= 500) & (BANDS <= 2000)


@lru_cache(maxsize=8)
def lattice(order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """q (K, 3), m (K, 3) and the reflection counts (K, 6) (-x, +x, -y, +y, -z, +z) of every image with
    1 <= total reflections <= order."""
    qs, ms, counts = [], [], []
    rng = range(-order, order + 1)
    for q in itertools.product((0, 1), repeat=3):
        for m in itertools.product(rng, repeat=3):
            c = []
            for a in range(3):
                c += [abs(m[a] - q[a]), abs(m[a])]
            if 1 <= sum(c) <= order:
                qs.append(q)
                ms.append(m)
                counts.append(c)
    return np.array(qs, float), np.array(ms, float), np.array(counts, float)


def wall_reflectance(materials) -> np.ndarray:
    """Amplitude reflection factor (6,) of the proxy box's walls (-x, +x, -y, +y, -z, +z)."""
    r = []
    for name in materials:
        if name == "Transparent":
            r.append(0.0)
        else:
            a = float(np.mean(np.asarray(get_material(name).absorption)[MID_BANDS]))
            r.append(np.sqrt(max(0.0, 1.0 - a)))
    return np.array(r)


def image_amplitudes(reflect: np.ndarray, order: int) -> np.ndarray:
    """Amplitude factor (K,) of every image of the lattice: the product of its walls' reflection factors
    (the image positions themselves are placed per block by ``kernels.image_taps``)."""
    c = lattice(order)[2]
    return np.prod(np.where(c > 0, reflect[None, :] ** c, 1.0), axis=1)
