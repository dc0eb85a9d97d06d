"""`sonicverse bench train`: the learned agents' training throughput on this machine.

* **Rollout** (one process): the AV-Nav policy acting in one env, frames/s, with the environment's share (rendering,
  audio, physics: ``env.step``) and the model's (quantising the observation, one forward step of the encoders and the
  GRU), for audio + depth and for audio only (no camera, no depth encoder); torch acts on one thread
  (:func:`agents.models.acting_threads`), and once more on torch's default threads to show what that costs.
* **Update**: the imitation update (forward over 48-step chunks of 16 sequences, backward, Adam) in frames/s.
* **Models** (``agents``): the rollout and the update of SAVi and the multi-task model (audio + depth) beside
  AV-Nav's, so what the scene memory and the occupancy U-Net cost shows against the same env.
* **Devices** (``--devices cpu cuda``): each model's rollout (acting on a batch of one between env steps) and
  update with its weights on each device, in the same run; CUDA times end with a synchronisation.
* **Vector**: rollout steps/s in total against the number of subprocess workers (Gymnasium AsyncVectorEnv), with
  the workers' threads shared out over the cores (the default) and with the libraries' own defaults (Mesa's
  llvmpipe starts a rasteriser thread per core in every worker).

The reference, measured in the same run, is the env stepping alone in this process (``env_only_steps_per_s``):
the rollout's ratio to it is what the model costs.
"""
from __future__ import annotations

import time

import numpy as np

AUDIO_DEPTH = ("depth", "spectrogram", "pose")
AUDIO_ONLY = ("spectrogram", "pose")


def _model(env, sensors, size: int, agent: str = "av-nav", task: str = "AudioGoal"):
    import torch

    from agents.imitation import ImitationConfig, build_policy

    torch.manual_seed(0)
    adim = env.single_action_space.shape[0] if hasattr(env, "single_action_space") else env.action_space.shape[0]
    spec = (env.single_observation_space if hasattr(env, "single_observation_space")
            else env.observation_space)["spectrogram"].shape
    if "depth" not in sensors:  # audio only (AV-Nav without its depth encoder)
        from agents.models import AVNav, AVNavConfig, primitives_for

        return AVNav(AVNavConfig(depth_hw=(), spec_shape=spec, action_dim=adim, primitives=primitives_for(adim),
                                 aux_goal=True)).eval()
    return build_policy(ImitationConfig(task=task, agent=agent, size=size), spec, adim).eval()


def _tensors(obs, batched: bool, device=None):
    """The model's inputs (T = 1, B) from an observation (or a vector env's stacked observations), quantised as the
    training data is (:func:`agents.imitation._quantise`), on ``device``."""
    import torch

    from agents.imitation import _inputs, _quantise, _stack

    if not batched:
        return _inputs(*_stack([obs]), device)
    return _inputs(*(None if x is None else torch.from_numpy(x)[None] for x in _quantise(obs)), device)


def _sync(device) -> None:
    import torch

    if device is not None and torch.device(device).type == "cuda":
        torch.cuda.synchronize(device)


def rollout_one(task: str, sensors: tuple, steps: int, size: int, seed: int, threads: int | None = 1,
                agent: str = "av-nav", device: str = "cpu") -> dict:
    """``threads``: torch's threads while acting (:func:`agents.models.acting_threads`; None: torch's default)."""
    import contextlib

    import torch

    from agents.models import acting_threads
    from sonicverse_core.tasks import make_env

    env = make_env(task, split="train", homes=1, sensors=sensors, width=size, height=size)
    try:
        model = _model(env, sensors, size, agent, task).to(device)
        obs, _ = env.reset(seed=seed)
        h, start = model.initial_state(1), True
        t_env = t_model = 0.0
        for i in range(steps + 10):  # 10 warm-up steps (GL context, caches)
            if i == 10:
                t_env = t_model = 0.0
            t0 = time.perf_counter()
            with torch.no_grad(), (acting_threads(threads) if threads else contextlib.nullcontext()):
                d, s, p = _tensors(obs, batched=False, device=device)
                out, _, h = model(d, s, p, h, torch.tensor([[start]], device=device))
                a = model.act(out)[0, 0].cpu().numpy()  # (the copy back waits for the device)
            t1 = time.perf_counter()
            obs, _, term, trunc, _ = env.step(a.astype(np.float32))
            start = term or trunc
            if start:
                obs, _ = env.reset()
            t2 = time.perf_counter()
            t_model += t1 - t0
            t_env += t2 - t1
        # the reference: the env alone, the same number of steps, in this process
        rng = np.random.default_rng(seed)
        env.reset(seed=seed)
        t0 = time.perf_counter()
        for _ in range(steps):
            _, _, term, trunc, _ = env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32))
            if term or trunc:
                env.reset()
        env_only = steps / (time.perf_counter() - t0)
    finally:
        env.close()
    total = t_env + t_model
    return {"sensors": list(sensors), "frames_per_s": round(steps / total, 1), "env_share": round(t_env / total, 3),
            "model_share": round(t_model / total, 3), "env_ms": round(1000 * t_env / steps, 3),
            "model_ms": round(1000 * t_model / steps, 3), "env_only_steps_per_s": round(env_only, 1),
            "ratio_to_env_only": round(steps / total / env_only, 3),
            "parameters": int(sum(p.numel() for p in model.parameters())), "device": str(device)}


def update(task: str, sensors: tuple, size: int, reps: int = 4, seq: int = 48, batch: int = 16,
           agent: str = "av-nav", device: str = "cpu") -> dict:
    """Frames/s of the imitation update on random data of the training data's shapes and types."""
    import torch

    from agents.imitation import bc_loss
    from agents.models import primitives_for
    from sonicverse_core.tasks import make_env

    env = make_env(task, split="train", homes=1, sensors=sensors, width=size, height=size)
    try:
        model = _model(env, sensors, size, agent, task).to(device).train()
        spec = env.observation_space["spectrogram"].shape
        adim = env.action_space.shape[0]
    finally:
        env.close()
    g = torch.Generator().manual_seed(0)
    table = torch.tensor(primitives_for(adim))
    b = {"s": torch.randint(0, 255, (seq, batch) + spec, generator=g, dtype=torch.uint8),
         "p": torch.randn(seq, batch, 4, generator=g), "g": torch.randn(seq, batch, 3, generator=g),
         "a": table[torch.randint(0, len(table), (seq, batch), generator=g)], "m": torch.ones(seq, batch)}
    b["d"] = (torch.randint(0, 255, (seq, batch, size, size), generator=g, dtype=torch.uint8) if "depth" in sensors
              else None)
    if getattr(model, "category", None) is not None:  # SAVi's targets
        b["c"] = torch.randint(0, model.cfg.n_categories, (seq, batch), generator=g)
    if getattr(model.cfg, "occupancy", 0):
        V = model.cfg.occupancy
        b["o"] = torch.randint(0, 2, (seq, batch, V, V), generator=g, dtype=torch.uint8)
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)

    def step():
        loss, _ = bc_loss(model, b, 0.5)
        opt.zero_grad()
        loss.backward()
        opt.step()

    step()  # warm-up
    _sync(device)
    t0 = time.perf_counter()
    for _ in range(reps):
        step()
    _sync(device)
    dt = time.perf_counter() - t0
    return {"frames_per_s": round(reps * seq * batch / dt, 1), "batch_frames": seq * batch,
            "ms_per_batch": round(1000 * dt / reps, 1)}


def rollout_vector(task: str, workers: int, steps: int, size: int, seed: int, threads) -> dict:
    """The policy acting in ``workers`` subprocess envs (audio + depth), batched over the envs."""
    import torch

    from agents.models import acting_threads
    from sonicverse_core.tasks import make_vector_env, worker_threads

    envs = make_vector_env(task, workers, threads=threads, split="train", homes=1, sensors=AUDIO_DEPTH, width=size,
                           height=size)
    try:
        model = _model(envs, AUDIO_DEPTH, size, task=task)
        obs, _ = envs.reset(seed=seed)
        h, starts = model.initial_state(workers), torch.ones(1, workers)
        n = max(steps // workers, 20)
        t_env = t_model = 0.0
        for i in range(n + 5):
            if i == 5:
                t_env = t_model = 0.0
            t0 = time.perf_counter()
            with torch.no_grad(), acting_threads():
                d, s, p = _tensors(obs, batched=True)
                out, _, h = model(d, s, p, h, starts)
                a = model.act(out)[0].numpy().astype(np.float32)
            t1 = time.perf_counter()
            obs, _, term, trunc, _ = envs.step(a)
            starts = torch.from_numpy((term | trunc).astype(np.float32))[None]
            t2 = time.perf_counter()
            t_model += t1 - t0
            t_env += t2 - t1
    finally:
        envs.close()
    total = n * workers / (t_env + t_model)
    return {"workers": workers, "threads_per_worker": worker_threads(workers) if threads == -1 else "default",
            "steps_per_s_total": round(total, 1), "steps_per_s_per_env": round(total / workers, 1),
            "model_share": round(t_model / (t_env + t_model), 3)}


def bench_train(task: str = "AudioGoal", steps: int = 300, workers=(1, 2), size: int = 64, seed: int = 0,
                agents=("av-nav",), devices=("cpu",), update_batches: int = 4,
                update_sequences: int = 16) -> dict:
    """``update_batches``: imitation batches timed per update measurement (after one warm-up batch) of
    ``update_sequences`` sequences of 48 steps (the imitation recipe's batch: 16)."""
    import torch

    from agents.models import resolve_device
    from sonicverse_core.tasks import cores

    for dv in devices:
        resolve_device(dv)  # cuda without a CUDA device: a ConfigError before anything runs
    out = {"bench": "train", "task": task, "size": size, "steps": steps, "update_batches": update_batches,
           "update_sequences": update_sequences,
           "torch_threads": torch.get_num_threads(),
           "cores": cores()}
    for name, sensors in (("audio_depth", AUDIO_DEPTH), ("audio_only", AUDIO_ONLY)):
        out[name] = {"rollout": rollout_one(task, sensors, steps, size, seed),
                     "update": update(task, sensors, size, reps=update_batches, batch=update_sequences)}
    # what acting with torch's default threads costs (its OpenMP workers spin between steps beside the renderer)
    r = rollout_one(task, AUDIO_DEPTH, steps, size, seed, threads=None)
    out["audio_depth"]["rollout_torch_default_threads"] = {k: r[k] for k in ("frames_per_s", "env_ms", "model_ms")}
    if set(agents) - {"av-nav"}:
        keys = ("frames_per_s", "model_ms", "env_ms", "ratio_to_env_only", "parameters")
        models = {}
        for agent in agents:
            r = out["audio_depth"]["rollout"] if agent == "av-nav" else rollout_one(task, AUDIO_DEPTH, steps, size,
                                                                                    seed, agent=agent)
            u = (out["audio_depth"]["update"] if agent == "av-nav"
                 else update(task, AUDIO_DEPTH, size, agent=agent, reps=update_batches, batch=update_sequences))
            models[agent] = {"rollout": {k: r[k] for k in keys}, "update_frames_per_s": u["frames_per_s"]}
        out["models"] = models
    if set(devices) - {"cpu"}:  # every model on every device, side by side (audio + depth)
        keys = ("frames_per_s", "model_ms", "env_ms", "ratio_to_env_only")
        per = {}
        for dv in devices:
            per[dv] = {}
            for agent in agents:
                r = rollout_one(task, AUDIO_DEPTH, steps, size, seed, agent=agent, device=dv)
                u = update(task, AUDIO_DEPTH, size, agent=agent, device=dv, reps=update_batches,
                           batch=update_sequences)
                per[dv][agent] = {"rollout": {k: r[k] for k in keys}, "update_frames_per_s": u["frames_per_s"],
                                  "update_ms_per_batch": u["ms_per_batch"]}
        out["devices"] = per
        gpu = next(dv for dv in devices if dv != "cpu")
        out["device_name"] = torch.cuda.get_device_name(0)
        if "cpu" in devices:
            out["update_speedup"] = {ag: round(per[gpu][ag]["update_frames_per_s"] / per["cpu"][ag]
                                               ["update_frames_per_s"], 2) for ag in agents}
            out["rollout_speedup"] = {ag: round(per[gpu][ag]["rollout"]["frames_per_s"] / per["cpu"][ag]["rollout"]
                                                ["frames_per_s"], 2) for ag in agents}
    vec = []
    for w in workers:
        for threads in (-1, None):
            vec.append(rollout_vector(task, w, steps, size, seed, threads))
    out["vector"] = vec
    one = out["audio_depth"]["rollout"]["frames_per_s"]
    out["vector_vs_one_process"] = {f"{r['workers']}x{r['threads_per_worker']}": round(r["steps_per_s_total"] / one, 2)
                                    for r in vec}
    return out
