"""`sonicverse bench env`: environment steps per second, one env and N vectorised workers, with a breakdown.

Reference measured in the same run: the bare pyrender depth render of the same view (what any simulator with a
depth camera pays at least); ``overhead_vs_depth_render`` = steps/s of the env / renders/s of the camera alone.
SoundSpaces 2.0 reports about 2.5 steps/s per env with audio on an RTX 3090 (constant, for scale).
"""
from __future__ import annotations

import time

import numpy as np

SOUNDSPACES2_STEPS_PER_S = 2.5


def _actions(rng, n, dim):
    a = rng.uniform(-1, 1, (n, dim)).astype(np.float32)
    a[:, :2] = 0.6 * a[:, :2] + 0.4  # mostly forward: the robot explores instead of spinning in place
    if dim == 3:
        a[:, 2] = -1.0
    return a


def _run(env, actions, seed: int, desc: str = "") -> float:
    from sonicverse_core.progress import progress

    env.reset(seed=seed)
    t0 = time.perf_counter()
    for a in progress(actions, len(actions), desc, enabled=bool(desc)):  # a bar on a terminal, else 4 log lines
        _, _, term, trunc, _ = env.step(a)
        if term or trunc:
            env.reset()
    return len(actions) / (time.perf_counter() - t0)


def bench_env(task: str = "AudioGoal", steps: int = 400, workers: int = 2, size: int = 128, seed: int = 0) -> dict:
    from app.tasks.evaluate import make_env

    rng = np.random.default_rng(seed)
    sensors = ("depth", "audio", "spectrogram", "bump", "pose")
    env = make_env(task, split="test", homes=1, sensors=sensors, width=size, height=size)
    actions = _actions(rng, steps, env.action_space.shape[0])
    _run(env, actions[:20], seed)  # warm-up: numba, GL context, bake cache
    sps = _run(env, actions, seed, "env steps")
    # breakdown: each part timed alone on the same env
    u = env
    w = u.home.world
    parts = {}

    def timeit(name, fn, n=200):
        fn()
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        parts[name] = 1000 * (time.perf_counter() - t0) / n

    a2 = np.array([0.5, 0.5])
    pose = w.pose.copy()

    def physics():
        w.pose = pose.copy()
        w.drive(a2, u.cfg.step_seconds)

    timeit("physics_ms", physics)
    w.pose = pose
    timeit("audio_render_ms", u._render_audio)
    movable = [o for o in w.scene.objects if o.movable]
    if movable:  # the robot carrying an object (as in voice retrieval), 1 cm back and forth a step: every source's
        o, home = movable[0], movable[0].pose.copy()  # sound to the ears passes by it, so the occlusion recasts
        w.carried = o.name

        def carried():
            w.pose = pose + (0.01 * (w.pose[0] == pose[0]), 0.0, 0.0)
            w._carry_along()
            u._render_audio()

        timeit("audio_render_carrying_ms", carried, n=100)
        w.carried, w.pose = None, pose
        w.scene.move_object(o.name, home)
    block = np.zeros((2, u.spb), np.float32)
    timeit("spectrogram_ms", lambda: u._spec.push(block))
    cam = u._camera()
    timeit("depth_render_ms", lambda: cam.render(*w.camera))
    parts["step_total_ms"] = 1000.0 / sps
    parts["other_ms"] = parts["step_total_ms"] - sum(v for k, v in parts.items()
                                                     if k not in ("step_total_ms", "audio_render_carrying_ms"))
    depth_fps = 1000.0 / parts["depth_render_ms"]
    env.close()
    # the same env with the RGB camera on (the home's look): what RGB-D costs a step
    env = make_env(task, split="test", homes=1, sensors=("rgb",) + sensors, width=size, height=size)
    _run(env, actions[:20], seed)
    sps_rgb = _run(env, actions, seed, "env steps with RGB")
    cam = env._camera()
    w = env.home.world
    n = 200
    cam.render(*w.camera)
    t0 = time.perf_counter()
    for _ in range(n):
        cam.render(*w.camera)
    rgbd_fps = n / (time.perf_counter() - t0)
    env.close()

    out = {"bench": "env", "task": task, "sensors": list(sensors), "size": size, "steps": steps,
           "steps_per_s": round(sps, 1), "breakdown_ms": {k: round(v, 3) for k, v in parts.items()},
           "reference_depth_renders_per_s": round(depth_fps, 1),
           "overhead_vs_depth_render": round(sps / depth_fps, 3),
           "vs_soundspaces2": round(sps / SOUNDSPACES2_STEPS_PER_S, 1),
           "with_rgb": {"steps_per_s": round(sps_rgb, 1), "rgbd_renders_per_s": round(rgbd_fps, 1),
                        "cost_vs_without": round(sps / sps_rgb, 2)},
           "audio": "16 kHz binaural, 0.1 s per step, direct + occlusion + early reflections + late reverb"}
    if workers > 0:
        out["vector"] = bench_vector(task, workers, steps, size, seed)
    return out


def bench_vector(task: str, workers: int, steps: int, size: int, seed: int) -> dict:
    """N subprocess workers (Gymnasium AsyncVectorEnv; each creates its own GL context) with RGB + depth + audio."""
    from sonicverse_core.tasks import make_vector_env

    kw = dict(split="test", homes=1, sensors=("rgb", "depth", "audio", "spectrogram", "bump", "pose"), width=size,
              height=size)
    envs = make_vector_env(task, workers, **kw)
    try:
        rng = np.random.default_rng(seed)
        dim = envs.single_action_space.shape[0]
        envs.reset(seed=seed)
        for _ in range(10):
            envs.step(_actions(rng, workers, dim))
        n = max(steps // workers, 50)
        t0 = time.perf_counter()
        from sonicverse_core.progress import progress

        for _ in progress(range(n), n, f"{workers} workers' steps"):
            envs.step(_actions(rng, workers, dim))
        dt = time.perf_counter() - t0
    finally:
        envs.close()
    total = n * workers / dt
    return {"workers": workers, "sensors": list(kw["sensors"]), "steps_per_s_total": round(total, 1),
            "steps_per_s_per_env": round(total / workers, 1)}
