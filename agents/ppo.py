"""PPO fine-tuning of a learned policy (the second stage of the recipe, after imitation), on one process or many.

Recurrent PPO (Schulman et al. 2017) with generalised advantage estimation over rollouts of ``steps`` steps in
``envs`` environments per process; the GRU's state at each rollout's start is kept, and the update replays whole
rollouts per environment (episode starts inside them reset the state, as in acting). The policy is the AV-Nav model
(:mod:`agents.models`): a categorical over the discrete head's primitives or a Gaussian around the continuous head's
mean. It starts from a checkpoint (``init``, normally the imitation's ``best.pt``; its value head is untrained, so
the first ``critic_warmup`` updates train the value head alone) or from scratch. From a checkpoint the loss adds
``kl_init`` x KL(the starting policy || the policy) on the rollouts' states: a first run without it (entropy bonus
0.01) drifted away from the imitation policy and lost all its successes within 56k frames.

A policy with a map input (``train --map``) is fine-tuned as it plays: each env has its own egocentric map
(:func:`agents.maps.ego_for`), drawn once per observation, and where the policy reads the task's floor plan the
floor shield's allowed actions mask its distribution in the rollouts, the update and the KL alike. Each log row's
``replay_err`` is the largest |ratio - 1| of the update's first pass, before any step: the update replays what acted.

**Beyond one process (DD-PPO, Wijmans et al. 2020)**: launched by ``torchrun --nproc_per_node=K -m agents.train``
(or ``sonicverse train --nproc K``), every process collects its own rollouts and the gradients are averaged with
``torch.distributed`` (gloo on CPU, NCCL on CUDA) after each backward pass, so the weights stay identical. Stragglers
are pre-empted as DD-PPO does: once ``preempt`` of the processes have finished their rollouts, the others stop theirs
early (after at least a quarter of ``steps``), counted through the process group's key-value store.

Why not a library: the recurrent, multi-input policy with episode-start masks, started from imitation weights, and
DD-PPO's pre-emption fit neither Stable-Baselines3 (no recurrent PPO with dict observations in the core, no
distributed training) nor torchrl's collectors without wrapping the model in TensorDict modules; this file is the
whole algorithm.
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from agents.imitation import NAV_VAL, VAL_KEYS, _inputs, _map_input, _stack, append_row, evaluate
from agents.maps import SENSORS, ego_for, floor_shield, sensors_for
from agents.models import (AVNav, AVNavConfig, acting_threads, load_policy, head_primitives, resolve_device,
                           save_policy as save)


@dataclass
class PPOConfig:
    task: str = "AudioGoal"
    frames: int = 20_000  # total over all processes
    envs: int = 2  # per process
    steps: int = 64  # rollout length per env
    epochs: int = 2
    lr: float = 2.5e-5
    clip: float = 0.2
    gamma: float = 0.99
    lam: float = 0.95
    entropy: float = 0.0  # fine-tuning; a policy trained from scratch wants some (0.01)
    kl_init: float = 0.1  # weight of KL(init policy || policy) on the rollouts (0: none; needs init)
    value_coef: float = 0.5
    max_grad_norm: float = 0.5
    size: int = 64
    seed: int = 0
    init: str | None = None  # a checkpoint to start from (the imitation's best.pt)
    head: str = "discrete"  # from scratch only
    val_episodes: int = 8
    val_every: int = 20  # updates
    critic_warmup: int = 10  # updates that train only the value head (a checkpoint from imitation has none)
    preempt: float = 0.6  # DD-PPO: the share of processes whose finishing pre-empts the rest
    device: str = "cpu"  # cpu, cuda or auto (resolve_device): where the model acts and trains
    homes: int = 0  # train homes to draw episodes from: the split's first N (0: its default, 16)


class Dist:
    """The process group (``torchrun`` sets RANK / WORLD_SIZE / MASTER_ADDR), or a group of one."""

    def __init__(self, device: torch.device = torch.device("cpu")):
        import os

        self.on = "WORLD_SIZE" in os.environ and int(os.environ["WORLD_SIZE"]) > 1
        self.device = device
        if self.on:
            import torch.distributed as dist

            if not dist.is_initialized():
                dist.init_process_group(self.backend_for(device))
            self.dist = dist
            self.rank, self.world = dist.get_rank(), dist.get_world_size()
            self.store = dist.distributed_c10d._get_default_store()
        else:
            self.rank, self.world = 0, 1

    @staticmethod
    def backend_for(device: torch.device) -> str:
        """NCCL for a model on CUDA with a GPU per process on the node; gloo on the CPU, and where the node's
        processes outnumber its GPUs (NCCL refuses two ranks on one device; gloo reduces CUDA tensors too)."""
        import os

        if device.type != "cuda":
            return "gloo"
        local = int(os.environ.get("LOCAL_WORLD_SIZE", os.environ.get("WORLD_SIZE", "1")))
        return "nccl" if local <= torch.cuda.device_count() else "gloo"

    def average_grads(self, model) -> None:
        if not self.on:
            return
        grads = [p.grad for p in model.parameters() if p.grad is not None]
        flat = torch.cat([g.reshape(-1) for g in grads])
        self.dist.all_reduce(flat)
        flat /= self.world
        i = 0
        for g in grads:
            g.copy_(flat[i:i + g.numel()].view_as(g))
            i += g.numel()

    def broadcast(self, model) -> None:
        if self.on:
            for t in model.state_dict().values():
                self.dist.broadcast(t, 0)

    def finished(self, update: int) -> int:
        """Mark this process's rollout of ``update`` done; the number done so far."""
        return int(self.store.add(f"done{update}", 1)) if self.on else 1

    def done_count(self, update: int) -> int:
        return int(self.store.add(f"done{update}", 0)) if self.on else 0

    def sum(self, x: float) -> float:
        if not self.on:
            return x
        t = torch.tensor([x], dtype=torch.float64, device=self.device)
        self.dist.all_reduce(t)
        return float(t[0])

    def spread(self, x: float) -> float:
        """max - min of ``x`` over the processes (0 for one)."""
        if not self.on:
            return 0.0
        hi = torch.tensor([x], dtype=torch.float64, device=self.device)
        lo = hi.clone()
        self.dist.all_reduce(hi, op=self.dist.ReduceOp.MAX)
        self.dist.all_reduce(lo, op=self.dist.ReduceOp.MIN)
        return float(hi[0] - lo[0])

    def barrier(self) -> None:
        if self.on:
            self.dist.barrier()

    def close(self) -> None:
        if self.on:
            self.dist.destroy_process_group()


def _dist_of(model: AVNav, out: torch.Tensor, allowed: torch.Tensor | None = None):
    """The policy's action distribution from its head's output; ``allowed`` (bool, the output's shape; discrete
    head) removes the actions the floor shield forbids, as the agent plays (rows where it forbids every action keep
    them all, as :func:`agents.imitation._policy_step` does)."""
    if model.discrete:
        if allowed is not None:
            keep = allowed | ~allowed.any(-1, keepdim=True)
            out = out.masked_fill(~keep, -1e9)
        return torch.distributions.Categorical(logits=out)
    return torch.distributions.Normal(out, model.log_std.exp())


class _Maps:
    """The egocentric maps of a map policy's envs (one :func:`agents.maps.ego_for` each), drawn once per
    observation (a map's belief moves on with every ``observe``), with the floor shield's allowed actions at that
    step: the same maps and the same shield the ``av-nav`` agent plays with. Empty for a policy without a map."""

    def __init__(self, model, n: int):
        self.model = model
        self.egos = [ego_for(model) for _ in range(n)]
        self.on = self.egos[0] is not None if n else False
        self.maps: list = [None] * n
        self.allowed: list = [None] * n

    def reset(self, i: int, env, obs, info) -> None:
        if self.on:
            self.egos[i].reset(env, obs, info)
            self.see(i, obs, info)

    def see(self, i: int, obs, info) -> None:
        if self.on:
            self.maps[i] = np.ascontiguousarray(self.egos[i].observe(obs, info))
            ok = floor_shield(self.model, self.egos[i])
            n = len(self.model.table) if self.model.discrete else 1
            self.allowed[i] = np.ones(n, bool) if ok is None else np.asarray(ok, bool)

    def now(self, device) -> tuple:
        """(the maps as uint8 (1, E, C, H, W), the allowed actions (1, E, A)) on ``device``; (None, None) without."""
        if not self.on:
            return None, None
        return (torch.from_numpy(np.stack(self.maps))[None].to(device),
                torch.from_numpy(np.stack(self.allowed))[None].to(device))


def train(cfg: PPOConfig, out, progress=None) -> dict:
    """Run PPO for ``cfg.frames`` frames (all processes together); rank 0 writes ``out/model.pt`` (every
    ``val_every`` updates, validated or not: an interrupted run keeps it), ``out/best.pt`` (the best validation
    SR + SPL) and ``out/log.csv``."""
    from sonicverse_core.errors import ConfigError
    from sonicverse_core.tasks import make_env

    import os

    dev = resolve_device(cfg.device)
    if dev.type == "cuda" and "LOCAL_RANK" in os.environ:  # torchrun: one GPU per process on a node
        dev = torch.device("cuda", int(os.environ["LOCAL_RANK"]) % torch.cuda.device_count())
        torch.cuda.set_device(dev)
    dist = Dist(dev)
    out = Path(out)
    if dist.rank == 0 and (out / "model.pt").exists():
        raise ConfigError(f"{out / 'model.pt'} exists: choose another --out")
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng([cfg.seed, dist.rank])

    def make_envs(sensors):
        return [make_env(cfg.task, split="train", sensors=sensors, width=cfg.size, height=cfg.size,
                         homes=cfg.homes or None) for _ in range(cfg.envs)]

    if cfg.init:
        model, meta = load_policy(cfg.init)  # AV-Nav, SAVi or the multi-task model
        from agents.learned import check_trained_on

        check_trained_on(cfg.init, meta, cfg.task)
        if getattr(model, "arch", None) == "ensemble":
            raise ConfigError(f"{cfg.init} is an ensemble of policies (train --ensemble): it acts, it does not train; "
                              "fine-tune one of its members")
        if hasattr(model, "stage"):
            model.stage(2)  # SAVi's second stage: the full memory, the encoders frozen
        size = model.cfg.depth_hw[0]
        if size != cfg.size:
            raise ConfigError(f"{cfg.init} was trained on {size} px depth, not --size {cfg.size}")
        envs = make_envs(sensors_for(model))  # a map policy's: what its map listens to (train --map)
    else:
        envs = make_envs(SENSORS)
        adim = envs[0].action_space.shape[0]
        model = AVNav(AVNavConfig(depth_hw=(cfg.size, cfg.size), spec_shape=envs[0].observation_space[
            "spectrogram"].shape, action_dim=adim, primitives=head_primitives(cfg.head, adim)))
    model.to(dev)
    dist.broadcast(model)
    ref = None
    if cfg.init and cfg.kl_init > 0:  # the starting policy, frozen
        import copy

        ref = copy.deepcopy(model).eval()
        for mod in ref.modules():  # a copied GRU's weights on CUDA are no longer one cuDNN chunk
            if isinstance(mod, torch.nn.RNNBase):
                mod.flatten_parameters()
        for q_ in ref.parameters():
            q_.requires_grad_(False)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    critic_ids = {id(q_) for q_ in model.critic.parameters()}
    not_critic = [q_ for q_ in model.parameters() if id(q_) not in critic_ids]
    E, T = cfg.envs, cfg.steps
    updates = max(1, math.ceil(cfg.frames / (E * T * dist.world)))
    maps = _Maps(model, E)
    obs = []
    for i, e in enumerate(envs):
        o, inf = e.reset(seed=int(rng.integers(2**31)))
        obs.append(o)
        maps.reset(i, e, o, inf)
    h = model.initial_state(E)
    h_ref = model.initial_state(E)
    start = torch.ones(E, device=dev)
    log_path = out / "log.csv"
    if dist.rank == 0:
        out.mkdir(parents=True, exist_ok=True)
    rows, best, frames, t0 = [], None, 0, time.perf_counter()
    ep_ret, ep_stats = np.zeros(E), []
    try:
        for u in range(updates):
            model.eval()
            h0 = h.clone()
            buf = {k: [] for k in ("d", "s", "p", "mp", "ok", "a", "logp", "v", "r", "start", "ref")}
            t_roll = time.perf_counter()
            n = 0
            for t in range(T):
                d, s, p = _stack(obs)
                d, s, p = (None if x is None else x.to(dev) for x in (d, s, p))
                mp, ok = maps.now(dev)
                kw = {} if mp is None else {"egomap": _map_input(mp)}
                with torch.no_grad(), acting_threads():
                    o, v, h = model(*_inputs(d, s, p), h, start[None], **kw)
                    if ref is not None:
                        o_ref, _, h_ref = ref(*_inputs(d, s, p), h_ref, start[None], **kw)
                        buf["ref"].append(o_ref[0])
                    pi = _dist_of(model, o[0], None if ok is None else ok[0])
                    a = pi.sample()
                    logp = pi.log_prob(a) if model.discrete else pi.log_prob(a).sum(-1)
                acts = (model.table[a] if model.discrete else a.clamp(-1, 1)).cpu()
                for k, x in zip(("d", "s", "p", "a", "logp", "v", "start"), (d[0], s[0], p[0], a, logp, v[0], start)):
                    buf[k].append(x)
                if mp is not None:
                    buf["mp"].append(mp[0])
                    buf["ok"].append(ok[0])
                rew, new_start = np.zeros(E, np.float32), torch.zeros(E, device=dev)
                for i, e in enumerate(envs):
                    obs[i], r, term, trunc, info = e.step(acts[i].numpy().astype(np.float32))
                    rew[i] = r
                    ep_ret[i] += r
                    if term or trunc:
                        m = info.get("metrics", {})
                        ep_stats.append((float(m.get("success", 0.0)), float(m.get("spl", 0.0)), ep_ret[i]))
                        ep_ret[i] = 0.0
                        obs[i], info = e.reset(seed=int(rng.integers(2**31)))
                        maps.reset(i, e, obs[i], info)
                        new_start[i] = 1.0
                    else:
                        maps.see(i, obs[i], info)
                buf["r"].append(torch.from_numpy(rew).to(dev))
                start = new_start
                n += E
                if dist.on and t + 1 >= T // 4 and dist.done_count(u) >= math.ceil(cfg.preempt * dist.world):
                    break  # DD-PPO: most processes are done, this straggler stops here
            dist.finished(u)
            roll_s = time.perf_counter() - t_roll
            frames += int(dist.sum(n))
            # bootstrap and advantages
            with torch.no_grad():
                mp, _ = maps.now(dev)
                kw = {} if mp is None else {"egomap": _map_input(mp)}
                _, v_last, _ = model(*_inputs(*_stack(obs), dev), h, start[None], **kw)
            L = len(buf["r"])
            B = {k: torch.stack(v) for k, v in buf.items() if v}  # (L, E, ...)
            adv = torch.zeros(L, E, device=dev)
            last = torch.zeros(E, device=dev)
            for t in reversed(range(L)):
                nxt_v = v_last[0] if t == L - 1 else B["v"][t + 1]
                nonterm = 1.0 - (start if t == L - 1 else B["start"][t + 1])
                delta = B["r"][t] + cfg.gamma * nxt_v * nonterm - B["v"][t]
                last = delta + cfg.gamma * cfg.lam * nonterm * last
                adv[t] = last
            ret = adv + B["v"]
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            # update: whole rollouts per env, from the state the rollout started in
            model.train()
            stats = []
            kw = {"egomap": _map_input(B["mp"])} if "mp" in B else {}
            ok = B.get("ok")
            for epoch in range(cfg.epochs):
                o, v, _ = model(*_inputs(B["d"], B["s"], B["p"]), h0, B["start"], **kw)
                pi = _dist_of(model, o, ok)
                logp = pi.log_prob(B["a"]) if model.discrete else pi.log_prob(B["a"]).sum(-1)
                ratio = (logp - B["logp"]).exp()
                if epoch == 0:  # before any step: the update replays what acted, so every ratio is 1
                    replay = float((ratio.detach() - 1).abs().max())
                pg = -torch.min(ratio * adv, ratio.clamp(1 - cfg.clip, 1 + cfg.clip) * adv).mean()
                vl = ((v - ret) ** 2).mean()
                ent = pi.entropy().mean() if model.discrete else pi.entropy().sum(-1).mean()
                warm = cfg.init is not None and u < cfg.critic_warmup
                loss = cfg.value_coef * vl if warm else pg + cfg.value_coef * vl - cfg.entropy * ent
                kl = torch.zeros((), device=dev)
                if ref is not None:
                    kl = torch.distributions.kl_divergence(_dist_of(ref, B["ref"], ok), pi)
                    kl = kl.mean() if model.discrete else kl.sum(-1).mean()
                    if not warm:
                        loss = loss + cfg.kl_init * kl
                opt.zero_grad()
                loss.backward()
                if warm:  # the value head alone: the shared encoders and GRU keep the imitation's policy
                    for q_ in not_critic:
                        if q_.grad is not None:
                            q_.grad.zero_()
                dist.average_grads(model)
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.max_grad_norm)
                opt.step()
                stats.append((float(pg.detach()), float(vl.detach()), float(ent.detach()),
                              float(((ratio - 1).abs() > cfg.clip).float().mean()), float(kl.detach())))
            h, h_ref = h.detach(), h_ref.detach()
            due = (u + 1) % cfg.val_every == 0 or u == updates - 1  # model.pt is written, with or without validation
            validate = cfg.val_episodes and due
            row = None
            if dist.rank == 0:
                model.eval()
                val = evaluate(model, cfg.task, cfg.val_episodes, "val", cfg.size, cfg.seed) if validate else {}
                recent = ep_stats[-20:]
                st = np.mean(stats, 0)
                row = {"update": u, "frames": frames, "processes": dist.world, "rollout_steps": L,
                       "rollout_fps": round(n / roll_s, 1), "policy_loss": round(st[0], 5),
                       "value_loss": round(st[1], 5), "entropy": round(st[2], 4), "clipped": round(st[3], 3),
                       "kl_init": round(st[4], 5), "replay_err": float(f"{replay:.3g}"),
                       "train_sr": round(float(np.mean([x[0] for x in recent])), 3) if recent else None,
                       "train_return": round(float(np.mean([x[2] for x in recent])), 3) if recent else None,
                       **{f"val_{k}": val.get(k) for k in VAL_KEYS.get(cfg.task, NAV_VAL)},
                       "param_sum": round(sum(float(p.detach().double().sum()) for p in model.parameters()), 6),
                       "wall_s": round(time.perf_counter() - t0, 1)}
                rows.append(row)
                append_row(log_path, row, first=u == 0)
                if due:
                    meta = {"recipe": "ppo", "config": asdict(cfg), "log": rows, "update": u}
                    save(model, out / "model.pt", meta)
                    score = sum(v or 0.0 for v in val.values())
                    if validate and (best is None or score > best):
                        best = score
                        save(model, out / "best.pt", meta)
                if progress is not None:
                    progress(row)
            dist.barrier()
        # the weights every process ends with: identical when the gradients were averaged
        spread = dist.spread(sum(float(p.detach().double().sum()) for p in model.parameters()))
    finally:
        for e in envs:
            e.close()
        dist.close()
    return {"out": str(out), "checkpoint": str(out / "model.pt"), "best": str(out / "best.pt"), "log": rows,
            "processes": dist.world, "rank": dist.rank, "param_spread": spread}
