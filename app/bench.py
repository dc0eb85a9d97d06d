"""Benchmarks: each measures against a reference in the same run and returns a JSON-able dict."""
from __future__ import annotations

import time

import numpy as np


def _rate(fn, n_items: int, min_time: float = 0.5, max_reps: int = 50) -> float:
    fn()  # warm-up
    reps, t0 = 0, time.perf_counter()
    while True:
        fn()
        reps += 1
        dt = time.perf_counter() - t0
        if dt >= min_time or reps >= max_reps:
            return n_items * reps / dt


def bench_rays(spec: str = "builtin:apartment", n_rays: int = 200_000, n_reference: int = 2_000,
               seed: int = 0) -> dict:
    """Rays per second through the Embree caster vs trimesh's pure-numpy caster, same scene, same kind of rays."""
    from sonicverse_core.geometry.raycast import RayCaster
    from sonicverse_core.scene.spec import load_scene

    scene = load_scene(spec)
    mesh = scene.static_mesh()
    rng = np.random.default_rng(seed)
    lo, hi = scene.bounds
    o = rng.uniform(lo + 0.2, hi - 0.2, (n_rays, 3))
    d = rng.normal(size=(n_rays, 3))
    embree = RayCaster(mesh, "embree")
    numpy_ = RayCaster(mesh, "numpy")
    r_embree = _rate(lambda: embree.first_hit(o, d), n_rays)
    r_numpy = _rate(lambda: numpy_.first_hit(o[:n_reference], d[:n_reference]), n_reference, max_reps=3)
    h1 = embree.first_hit(o[:n_reference], d[:n_reference])
    h2 = numpy_.first_hit(o[:n_reference], d[:n_reference])
    both = h1.hit & h2.hit
    return {
        "bench": "rays", "scene": spec, "triangles": len(mesh),
        "embree_rays_per_s": round(r_embree), "numpy_rays_per_s": round(r_numpy),
        "speedup": round(r_embree / r_numpy, 1),
        "agreement": {"same_hit_fraction": float(np.mean(h1.hit == h2.hit)),
                      "max_distance_error_m": float(np.max(np.abs(h1.distance[both] - h2.distance[both])))
                      if np.any(both) else 0.0},
    }
