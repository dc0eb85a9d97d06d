"""Navigation metrics, defined as in the papers everyone compares against.

* SR: fraction of successful episodes.
* SPL (Anderson et al. 2018): S * l / max(l, p), l = geodesic start-goal distance, p = the agent's path length.
* SNA (Chen et al. 2021, SAVi): S * n* / max(n*, n), n = actions taken (every step counts: collisions and turns in
  place included), n* = actions on the shortest path: the geodesic at top speed, ceil(l / (v_max * dt)).
* Distance to goal at the end (geodesic, m) and SoftSPL: (1 - d_end / l) * l / max(l, p).
Every metric is reported as ``{"mean": m, "ci95": [low, high], "n": n}``: a Wilson score interval for success
rates (exact-coverage-friendly at 0 or n successes, where a t-interval collapses to +-0) and a Student-t interval
for continuous per-episode values.
"""
from __future__ import annotations

import math

import numpy as np


def spl(success: bool, shortest: float, path: float) -> float:
    if not success:
        return 0.0
    if shortest <= 0:
        return 1.0
    return float(shortest / max(shortest, path))


def sna(success: bool, n_star: int, n: int) -> float:
    if not success:
        return 0.0
    return float(n_star / max(n_star, n, 1))


def soft_spl(shortest: float, path: float, d_end: float) -> float:
    if shortest <= 0:
        return 1.0
    progress = max(0.0, 1.0 - d_end / shortest)
    return float(progress * shortest / max(shortest, path))


def shortest_actions(shortest: float, max_speed: float, dt: float) -> int:
    return max(1, int(math.ceil(shortest / (max_speed * dt) - 1e-9)))


def mean_ci95(values) -> dict:
    """{'mean', 'ci95': [low, high] (Student t), 'median', 'n'} of continuous per-episode values; NaN values (an
    episode without that measure, e.g. an agent that reported no estimate) are left out and not counted in n."""
    x = np.asarray(list(values), float)
    x = x[~np.isnan(x)]
    n = len(x)
    if n == 0:
        return {"mean": None, "ci95": [None, None], "median": None, "n": 0}
    m, med = float(x.mean()), float(np.median(x))
    if n == 1:
        return {"mean": m, "ci95": [None, None], "median": med, "n": 1}
    from scipy import stats

    h = float(stats.t.ppf(0.975, n - 1) * x.std(ddof=1) / math.sqrt(n))
    return {"mean": m, "ci95": [m - h, m + h], "median": med, "n": n}


def rate_ci95(outcomes) -> dict:
    """{'mean', 'ci95': [low, high] (Wilson score, z = 1.96), 'n'} of 0/1 per-episode outcomes."""
    x = np.asarray(list(outcomes), float)
    n = len(x)
    if n == 0:
        return {"mean": None, "ci95": [None, None], "n": 0}
    p, z = float(x.mean()), 1.959963984540054
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z / den * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    low, high = max(0.0, centre - half), min(1.0, centre + half)
    # at p = 0 (1) the bound is exactly 0 (1); rounding would print 0.9999999999999999
    return {"mean": p, "ci95": [0.0 if p == 0 else low, 1.0 if p == 1 else high], "n": n}
