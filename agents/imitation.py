"""Imitation of the task's oracle with DAgger (Ross et al. 2011), the first stage of the learned agents'
recipe (behaviour cloning then PPO, as PIRLNav and SPOC do): far fewer frames than PPO from scratch.

Each iteration drives ``frames`` steps in train homes with a mix of the expert and the policy (the expert acts with
probability ``beta``, which decays to ``beta_min``; the policy takes its most likely action, or with ``learner``
"drawn" draws it as it plays, through the floor shield where it reads the floor plan; collection episodes end after
``rollout_steps``), labels every
visited state with the expert's action (the navigation oracle replans whenever the robot strays from its path; on
speaker following the expert is the oracle follower, :class:`FollowExpert`; where the task has a stop, a stop of the
policy's where the expert drives on is replaced by the expert's action, so that collection reaches the goal and its
stop label instead of ending short of it), adds them to a
bounded dataset of episode sequences, and fits the policy to the labels (cross-entropy over the discrete head's
primitives, or mean squared error of the continuous head's mean; truncated back-propagation through time over ``seq``
steps), with the auxiliary goal-prediction loss (``aux_weight``) on where the goal (the person) is from the robot.
Then it scores SR / SPL (catch success / time in band on speaker following) on validation homes with the policy
alone and saves a checkpoint and a CSV log line. ``resume`` goes on from ``out/model.pt`` (weights, optimizer,
random states, counters); the dataset is not saved (hundreds of MB) and refills from the next rollouts.

With ``jobs`` J > 1 the collection and validation run in J spawned processes (:class:`agents.dagger_jobs.Jobs`),
each with its own env and a copy of the policy as it stands at that iteration; the fit stays here. With ``teacher``
"scripted" and no map the labels are sem-nav's (:class:`SemNavExpert`; AudioGoal and SemanticAudioNav).

Observations are stored quantised to uint8 (depth over 0-10 m, spectrogram over 0-20): 10 KB a frame at 64 x 64.
"""
from __future__ import annotations

import csv
import math
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch

from agents.models import (DEPTH_MAX, SPEC_MAX, AVNav, AVNavConfig, acting_threads, load_policy, load_train_state,
                           head_primitives, resolve_device, save_policy as save)

from agents.maps import (MAP_TASKS, ROUTE_TASKS, allowed_actions, collect_sensors, ego_for, floor_shield, map_class,
                         map_kind_for, sensors_for)


@dataclass
class ImitationConfig:
    task: str = "AudioGoal"
    agent: str = "av-nav"  # or "savi", "multitask" (agents/savi.py)
    frames: int = 20_000  # total environment frames
    iterations: int = 10
    size: int = 64  # depth image side
    seq: int = 48
    batch: int = 16
    epochs: int = 4
    lr: float = 5e-4
    dataset_frames: int = 60_000
    val_episodes: int = 12
    head: str = "discrete"  # or "fine" (25 wheel pairs: primitives_for), "continuous"
    aux_weight: float = 0.5  # the goal-prediction loss (0: no goal heads)
    seed: int = 0
    beta0: float = 1.0  # the expert's share in the first iteration, decaying to beta_min by the middle of the run
    beta_min: float = 0.3  # (0 is DAgger's limit; here the learner's own stuck states then swamped the data)
    memory: int = 32  # savi / multitask: steps of scene memory (3.2 s; 64: 5.7 ms a step to act, 32: 3.4)
    occupancy: int = 32  # multitask: the occupancy map's V x V cells
    stage1: float = 1 / 3  # savi / multitask: the share of iterations in SAVi's first stage (memory of one step)
    goal_steps: int = 400  # savi / multitask: batches of the goal predictor's own training per first-stage iteration
    device: str = "cpu"  # where the model trains and acts: cpu, cuda or auto (resolve_device); not part of the recipe
    homes: int = 0  # train homes episodes are drawn from: the first N seeds of the train split (0: the split's
    # default, DEFAULT_HOMES["train"] = 16)
    egomap: bool = False  # an egocentric map input, any of the three policies (MAP_TASKS: EgoMap when following,
    # else NavEgoMap)
    route: bool = False  # with egomap on ROUTE_TASKS: RouteNavMap2, sem-nav's route drawn in (train --map route)
    teacher: str = "oracle"  # whose actions are the labels: the privileged "oracle", or (speaker following with
    # the map) the "scripted" follower, or (SemanticAudioNav with the map) sem-nav, which act on what the map
    # shows, so their labels do not ask for what the policy cannot know (the imitation gap); the goal heads still
    # learn where the person or the goal is from the oracle
    learner: str = "greedy"  # how the learner acts when DAgger lets it: its most likely action ("greedy"), or
    # "drawn" as it plays (drawn from its distribution, through the floor shield where it reads the floor plan)
    jobs: int = 1  # spawned processes that collect and validate (each its own env, GL context and copy of the
    # policy; the fit stays here). 1: all in this process. With J > 1 episode j of job k in iteration i draws from
    # seed (seed, 11, i, k, j), so a run is the same for the same J; validation is the same for any J. (Spawned: a
    # script calling train with jobs > 1 needs ``if __name__ == "__main__":``.)
    rollout_steps: int = 0  # a collection episode ends here (a stuck learner's 500 steps teach little); 0: the
    # task's own (200 on navigation, 600 on speaker following, whose episodes run 20-60 s to the catch at the end)


def _relative(pose, xy) -> np.ndarray:
    """Where ``xy`` is from a robot at ``pose`` (x, y, yaw in degrees): cos and sin of its bearing and log(1 +
    distance in m): the goal heads' target."""
    d = np.asarray(xy, float) - pose[:2]
    b = math.atan2(d[1], d[0]) - math.radians(pose[2])
    return np.array([math.cos(b), math.sin(b), math.log1p(math.hypot(*d))], np.float32)


class Expert:
    """The navigation oracle's action at whatever state the robot is in: its path is replanned when the robot is
    more than ``stray`` m from it or bumps."""

    def __init__(self, stray: float = 0.35):
        from agents.scripted import OracleAgent

        self.oracle = OracleAgent(np.random.default_rng(0))
        self.stray = stray

    def reset(self, env, obs, info) -> None:
        self.oracle.reset(env, obs, info)

    def category(self) -> int:
        """The goal's category (its index in the sound bank's categories): the SAVi goal predictor's target."""
        from assets_manifest.soundbank import CATEGORIES

        return CATEGORIES.index(self.oracle.env.unwrapped.episode.category)

    def goal(self) -> np.ndarray:
        """Where the goal (the middle of its terminal positions) is from the robot: cos and sin of its bearing and
        log(1 + distance in m): the auxiliary heads' target."""
        priv = self.oracle.env.privileged()
        return _relative(priv["world"].pose, np.mean(priv["goals"], axis=0))

    def label(self, obs, info) -> np.ndarray:
        o = self.oracle
        p = o.env.privileged()["world"].pose[:2]
        seg = o.path[max(o.k - 1, 0):o.k + 1]
        if len(seg) >= 2:
            a, b = seg[0], seg[1]
            t = np.clip(np.dot(p - a, b - a) / max(np.dot(b - a, b - a), 1e-12), 0, 1)
            if np.linalg.norm(a + t * (b - a) - p) > self.stray:
                o._plan()
        return o.act(obs, info)


class FollowExpert:
    """Speaker following's oracle (:class:`agents.following.OracleFollower`: the geodesic path to the person,
    holding 1.5 m while they walk, stepping out of their way, closing to 0.7 m and stopping at the end); the goal
    heads learn where the person is."""

    def __init__(self):
        from agents.following import OracleFollower

        self.oracle = OracleFollower(np.random.default_rng(0))

    def reset(self, env, obs, info) -> None:
        self.oracle.reset(env, obs, info)

    def category(self) -> int:
        return 0  # one kind of goal: the person

    def goal(self) -> np.ndarray:
        priv = self.oracle.env.privileged()
        return _relative(priv["world"].pose, priv["person"].pos)

    def label(self, obs, info) -> np.ndarray:
        return self.oracle.act(obs, info)


# per task: the expert, the collection episodes' length, the validation scores (summed to pick the best checkpoint)
EXPERTS = {"SpeakerFollowing": FollowExpert}
ROLLOUT_STEPS = {"SpeakerFollowing": 600}
VAL_KEYS = {"SpeakerFollowing": {"sr": "catch_success", "band": "time_in_band"}}
NAV_VAL = {"sr": "success", "spl": "spl"}


class SemNavExpert(Expert):
    """sem-nav's actions as the labels (``train --teacher scripted`` without ``--map`` on AudioGoal and
    SemanticAudioNav): :class:`agents.semnav.SemNavAgent` acts on the robot's own sensors (seeded by the episode),
    so its labels ask only for what the observations' history can tell: a turn on the spot to hear where the sound
    is, then the frontier nearest that bearing. The goal heads still learn where the goal is from the oracle."""

    def reset(self, env, obs, info) -> None:
        import zlib

        from agents.semnav import SemNavAgent

        super().reset(env, obs, info)
        self.teacher = SemNavAgent(np.random.default_rng(zlib.crc32(str(env.unwrapped.episode.episode_id).encode())))
        self.teacher.reset(env, obs, info)

    def label(self, obs, info) -> np.ndarray:
        return np.asarray(self.teacher.act(obs, info), np.float32)


def expert_for(task: str, cfg: "ImitationConfig | None" = None):
    """The labels' source for ``task``: the oracle (the oracle follower on speaker following), or sem-nav where
    ``cfg`` asks for the scripted teacher without a map (with a map the map's own scripted agent labels)."""
    if cfg is not None and cfg.teacher == "scripted" and not cfg.egomap:
        return SemNavExpert()
    return EXPERTS.get(task, Expert)()


def labellers(cfg: "ImitationConfig", model) -> tuple:
    """(expert, map) for collecting with ``model``: the labels' source (:func:`expert_for`) and the policy's map
    (None without one), whose own scripted agent labels where ``cfg.teacher`` is "scripted"."""
    ego = ego_for(model)
    if ego is not None and cfg.teacher == "scripted":
        ego.teach = True  # the map's own scripted agent acts (its action, ego.action, is the label)
    return expert_for(cfg.task, cfg), ego


def _quantise(obs) -> tuple:
    """(depth uint8 or None without a depth sensor, spectrogram uint8, pose float32) of an observation (or of a
    vector env's stacked observations): how the datasets store them."""
    d = (np.clip(np.round(obs["depth"][..., 0] / DEPTH_MAX * 255), 0, 255).astype(np.uint8) if "depth" in obs
         else None)
    s = np.clip(np.round(obs["spectrogram"] / SPEC_MAX * 255), 0, 255).astype(np.uint8)
    return d, s, obs["pose"].astype(np.float32)


def _stack(observations) -> tuple:
    """The quantised observations of several envs as tensors (1, B, ...) (depth None without a depth sensor)."""
    q = [_quantise(o) for o in observations]

    def t(i):
        return None if q[0][i] is None else torch.from_numpy(np.stack([x[i] for x in q]))[None]

    return t(0), t(1), t(2)


def _inputs(d, s, p, device=None) -> tuple:
    """The model's inputs from quantised tensors (``d`` may be None), on ``device`` (None: where they are)."""
    def f(x):
        return x.to(device, non_blocking=True).float() if device is not None else x.float()

    return (f(d)[..., None] * (DEPTH_MAX / 255) if d is not None else None, f(s) * (SPEC_MAX / 255), f(p))


def append_row(path, row: dict, first: bool) -> None:
    """A line of a training log (CSV); ``first`` starts the file with a header."""
    with open(path, "w" if first else "a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(row))
        if first:
            w.writeheader()
        w.writerow(row)


class Dataset:
    """Episode sequences of (depth, spectrogram, pose, expert action), oldest dropped past ``cap`` frames."""

    def __init__(self, cap: int):
        self.cap, self.eps = cap, []

    def add(self, ep: dict) -> None:
        self.eps.append({k: np.stack(v) for k, v in ep.items()})
        while sum(len(e["a"]) for e in self.eps) > self.cap and len(self.eps) > 1:
            self.eps.pop(0)

    @property
    def frames(self) -> int:
        return sum(len(e["a"]) for e in self.eps)

    def batches(self, rng, seq: int, batch: int):
        """Shuffled chunks of ``seq`` steps (each starting its GRU from zero: the chunk's first step is a start)."""
        chunks = [(i, s) for i, e in enumerate(self.eps) for s in range(0, len(e["a"]), seq)]
        order = rng.permutation(len(chunks))
        keys = list(self.eps[0]) if self.eps else []
        for k in range(0, len(order), batch):
            sel = [chunks[j] for j in order[k:k + batch]]
            T = seq
            out = {key: [] for key in keys + ["m"]}
            for i, s in sel:
                e = self.eps[i]
                n = min(T, len(e["a"]) - s)
                for key in keys:
                    x = e[key][s:s + n]
                    pad = np.zeros((T - n,) + x.shape[1:], x.dtype)
                    out[key].append(np.concatenate([x, pad]))
                out["m"].append(np.concatenate([np.ones(n, np.float32), np.zeros(T - n, np.float32)]))
            yield {k: torch.from_numpy(np.stack(v, 1)) for k, v in out.items()}  # (T, B, ...)


def _map_input(mp, device=None):
    """The model's egocentric map input in [0, 1] from uint8 (T, B, C, H, W) (None: none)."""
    if mp is None:
        return None
    x = mp.to(device, non_blocking=True) if device is not None else mp
    return x.float() * (1.0 / 255)


def _policy_step(model, obs, h, start: bool, rng: np.random.Generator | None = None, egomap=None, allowed=None,
                 temperature: float = 1.0, stop_at: float | None = None):
    """(action, next hidden state): the mean / most likely action, or with ``rng`` (discrete head) one drawn from
    the policy's distribution (raised to 1 / ``temperature``); a stop (tasks that have one) only when it is the most
    likely action or, with ``stop_at`` and ``rng``, when its probability reaches ``stop_at``; ``stop_at`` says a
    stop gate applies (:func:`agents.maps.allowed_actions`): where ``allowed`` lets the stop through, it is also
    drawn from the distribution as every other action (session 70), elsewhere never (it would end the episode).
    ``egomap``: the (C, H, W) uint8 map of a policy that reads one.
    ``allowed`` (discrete head): a bool per action; the others' probabilities are set to 0 before drawing or taking
    the most likely one, unless that leaves none."""
    dev = model.device
    kw = {} if egomap is None else {"egomap": _map_input(torch.from_numpy(np.ascontiguousarray(egomap))[None, None],
                                                         dev)}
    with torch.no_grad(), acting_threads():
        out, _, h = model(*_inputs(*_stack([obs]), dev), h, torch.tensor([[start]], device=dev), **kw)
    if model.discrete and (rng is not None or allowed is not None):
        prob = torch.softmax(out[0, 0].double(), -1).cpu().numpy()
        table = model.table.cpu().numpy()
        if allowed is not None and np.any(allowed & (prob > 0)):
            prob = np.where(allowed, prob, 0.0)
        best = int(np.argmax(prob))
        stop = table[:, 2] > 0 if table.shape[1] == 3 else np.zeros(len(prob), bool)
        if rng is None or stop[best]:  # the stop ends the episode: taken only when it is the most likely action
            return table[best], h
        if stop_at is not None and stop.any() and float(prob[stop].sum()) >= stop_at * float(prob.sum()):
            return table[int(np.argmax(np.where(stop, prob, -1.0)))], h
        if stop_at is None or allowed is None or not np.any(allowed & stop):
            prob = np.where(stop, 0.0, prob)  # a stop is drawn only where a gate lets it (stop_at: the gate applies)
        if temperature != 1.0:
            prob = prob / prob.max()  # 1 at the most likely action: no underflow of the power
            prob = prob ** (1.0 / temperature)
        return table[int(rng.choice(len(prob), p=prob / prob.sum()))], h
    return model.act(out)[0, 0].cpu().numpy(), h


def bc_loss(model, b: dict, aux_weight: float) -> tuple[torch.Tensor, dict]:
    """The imitation loss on a batch of chunks (``d`` depth uint8, ``s`` spectrogram uint8, ``p`` pose, ``a`` the
    expert's actions, ``g`` the goal targets (optional), ``m`` the mask of real steps): cross-entropy (discrete head)
    or squared error (continuous head), plus ``aux_weight`` x the goal heads' squared errors."""
    dev = model.device
    b = {k: None if v is None else v.to(dev, non_blocking=True) for k, v in b.items()}
    m = b["m"]
    starts = torch.zeros(m.shape, device=dev)
    starts[0] = 1.0
    kw = {"egomap": _map_input(b["mp"])} if b.get("mp") is not None else {}
    y, a_feat, _ = model.features(*_inputs(b.get("d"), b["s"], b["p"]), model.initial_state(m.shape[1]), starts, **kw)
    out = model.head(y)
    if model.discrete:
        per = torch.nn.functional.cross_entropy(out.reshape(-1, out.shape[-1]), model.label(b["a"]).reshape(-1),
                                                reduction="none").reshape(m.shape)
    else:
        per = ((out - b["a"]) ** 2).sum(-1)
    policy = (per * m).sum() / m.sum()
    parts = {"policy": float(policy.detach())}
    loss = policy
    if aux_weight > 0 and model.cfg.aux_goal and "g" in b:
        g = b["g"]
        goal = ((((model.goal_head(y) - g) ** 2).sum(-1)) * m).sum() / m.sum()
        audio = ((((model.goal_audio(a_feat) - g) ** 2).sum(-1)) * m).sum() / m.sum()
        parts.update(goal=float(goal.detach()), goal_audio=float(audio.detach()))
        loss = loss + aux_weight * (goal + audio)
    if hasattr(model, "extra_loss"):  # SAVi's category, the multi-task model's occupancy
        extra, more = model.extra_loss(b, y, a_feat, m)
        parts.update(more)
        loss = loss + extra
    return loss, parts


def pretrain_goal(model, data: Dataset, rng: np.random.Generator, steps: int, batch: int = 64,
                  lr: float = 1e-3) -> dict:
    """SAVi's goal predictor trained alone, as SAVi pretrains it: its spectrogram CNN, the category head and the
    location head on the dataset's audible frames (silent ones say nothing about the goal), ``steps`` batches of
    ``batch`` frames, gathered from the dataset's episodes (no copy of the dataset); the frames of 10% of the
    episodes are held out. Returns the held-out category accuracy and location error."""
    from agents.savi import AUDIBLE

    eps = data.eps
    loud = [np.flatnonzero(e["s"].reshape(len(e["s"]), -1).mean(1) * (SPEC_MAX / 255) > AUDIBLE) for e in eps]
    frames = np.array([(i, t) for i, ts in enumerate(loud) for t in ts], np.int64).reshape(-1, 2)  # (episode, step)
    if len(frames) < 20:
        return {}
    labelled = "c" in eps[0]
    held = rng.permutation(len(eps))[:max(len(eps) // 10, 1)]
    out_ = np.isin(frames[:, 0], held)
    test, train = np.flatnonzero(out_), np.flatnonzero(~out_)
    if len(test) == 0 or len(train) == 0:
        test = train = np.arange(len(frames))

    def gather(idx, key):
        return np.stack([eps[i][key][t] for i, t in frames[idx]])

    params = [p for m in (model.goal_net, model.goal_audio, model.category) if m is not None for p in m.parameters()]
    opt = torch.optim.Adam(params, lr=lr)

    dev = model.device

    def run(idx):
        def t(key):
            return torch.from_numpy(gather(idx, key)).to(dev)

        a = model.goal_net((t("s").float() / 255).clamp(0, 1))
        loc = ((model.goal_audio(a) - t("g")) ** 2).sum(-1).mean()
        ce = (torch.nn.functional.cross_entropy(model.category(a), t("c").long())
              if labelled else torch.zeros((), device=dev))
        return a, loc, ce

    model.train()
    for _ in range(steps):
        _, loc, ce = run(train[rng.integers(len(train), size=batch)])
        opt.zero_grad()
        (loc + ce).backward()
        opt.step()
    model.eval()
    with torch.no_grad():
        a, loc, _ = run(test)
        out = {"goal_audio_test": round(float(loc), 4), "audible_frames": int(len(frames))}
        if labelled:
            out["category_acc_test"] = round(float((model.category(a).argmax(1).cpu().numpy() == gather(test, "c")
                                                    ).mean()), 4)
    return out


def evaluate(model, task: str, episodes: int, split: str, size: int, seed: int = 0, jobs=None) -> dict:
    """The policy alone over ``episodes`` of ``split`` homes, acting as the ``av-nav`` agent does (actions drawn
    from the discrete head with a Generator seeded per episode, through the floor shield where the policy reads the
    floor plan and the stop gate where it reads sem-nav's route: :func:`agents.maps.allowed_actions`; the continuous
    head's mean): the means of the task's
    validation scores (``VAL_KEYS``: SR and SPL on navigation; on speaker following ``sr`` is the catch success and
    ``band`` the time in band). ``jobs``: a :class:`agents.dagger_jobs.Jobs` that plays them in its processes (the
    same scores)."""
    keys = VAL_KEYS.get(task, NAV_VAL)
    if jobs is not None:
        rows = jobs.evaluate(model, task, episodes, split, size, seed)
    else:
        from sonicverse_core.tasks import make_env

        env = make_env(task, split=split, sensors=sensors_for(model), width=size, height=size)
        try:
            rows = eval_episodes(model, env, ego_for(model), keys, range(episodes), seed)
        finally:
            env.close()
    return {k: float(np.mean([r[k] for r in rows])) for k in keys}


def eval_episodes(model, env, ego, keys: dict, indices, seed: int) -> list[dict]:
    """:func:`evaluate`'s episodes ``indices`` (each seeded by its index) in ``env``: a row of scores each."""
    rows = []
    for i in indices:
        obs, info = env.reset(seed=int(np.random.SeedSequence([seed, 7, i]).generate_state(1)[0]))
        h, start, done = model.initial_state(1), True, False
        draw = np.random.default_rng([seed, 8, i])
        if ego is not None:
            ego.reset(env, obs, info)
        while not done:
            mp = ego.observe(obs, info) if ego is not None else None
            allowed, stop_at = allowed_actions(model, ego)  # as the agents play: the floor shield or the stop gate
            a, h = _policy_step(model, obs, h, start, draw, mp, allowed, stop_at=stop_at)
            start = False
            obs, _, term, trunc, info = env.step(a.astype(np.float32))
            done = term or trunc
        m = info.get("metrics", {})
        rows.append({k: float(m.get(name, 0.0)) for k, name in keys.items()})
    return rows


def build_policy(cfg: ImitationConfig, spec_shape: tuple, action_dim: int):
    """The untrained policy ``cfg.agent`` names, for the env's spectrogram shape and action size."""
    prims = head_primitives(cfg.head, action_dim)
    kind = map_kind_for(cfg)
    M = map_class(kind)
    shape = (M.CHANNELS, M.SIZE, M.SIZE) if cfg.egomap else ()
    if cfg.agent == "av-nav":
        return AVNav(AVNavConfig(depth_hw=(cfg.size, cfg.size), spec_shape=spec_shape, action_dim=action_dim,
                                 primitives=prims, aux_goal=cfg.aux_weight > 0, map_shape=shape, map_kind=kind))
    from agents.savi import SAVi, SAViConfig
    from assets_manifest.soundbank import CATEGORIES

    return SAVi(SAViConfig(depth_hw=(cfg.size, cfg.size), spec_shape=spec_shape, action_dim=action_dim,
                           primitives=prims, memory=cfg.memory,
                           n_categories=0 if cfg.task in EXPERTS else len(CATEGORIES),
                           occupancy=cfg.occupancy if cfg.agent == "multitask" else 0, map_shape=shape, map_kind=kind))


def run_episode(model, env, expert, ego, cfg: ImitationConfig, rng: np.random.Generator, seed: int, beta: float,
                cap: int) -> dict:
    """One DAgger collection episode from ``env.reset(seed=seed)``: the expert acts with probability ``beta``, else
    the policy (its most likely action, or drawn with ``rng`` as ``cfg.learner`` says); every visited state is stored
    with the expert's label (sem-nav's or the scripted follower's action with ``cfg.teacher`` "scripted"). Ends at
    the episode's end or after ``cap`` steps. Returns the episode's lists (depth, spectrogram, pose, action, goal;
    the map, SAVi's category and the occupancy where the model has them)."""
    labels_c = getattr(model, "category", None) is not None  # SAVi's category targets
    occ_v = getattr(model.cfg, "occupancy", 0)  # the multi-task model's occupancy targets
    if occ_v:
        from agents.savi import true_occupancy
    obs, info = env.reset(seed=seed)
    expert.reset(env, obs, info)
    h, start, done = model.initial_state(1), True, False
    ep = {"d": [], "s": [], "p": [], "a": [], "g": []}
    if ego is not None:
        ego.reset(env, obs, info)
        ep["mp"] = []
    if labels_c:
        ep["c"] = []
    if occ_v:
        ep["o"] = []
    while not done:
        a_exp = expert.label(obs, info)
        mp = ego.observe(obs, info) if ego is not None else None
        if cfg.teacher == "scripted" and ego is not None:  # the map's own scripted agent (else SemNavExpert)
            a_exp = np.asarray(ego.action, np.float32)
        if cfg.learner == "drawn":
            a_pol, h = _policy_step(model, obs, h, start, rng, mp, floor_shield(model, ego))
        else:
            a_pol, h = _policy_step(model, obs, h, start, egomap=mp)
        if mp is not None:
            ep["mp"].append(mp.copy())
        d, s, p = _quantise(obs)
        ep["d"].append(d)
        ep["s"].append(s)
        ep["p"].append(p)
        ep["a"].append(a_exp.astype(np.float32))
        ep["g"].append(expert.goal())
        if labels_c:
            ep["c"].append(np.int64(expert.category()))
        if occ_v:
            ep["o"].append(true_occupancy(env.unwrapped.privileged()["world"], occ_v))
        start = False
        act = a_exp if rng.random() < beta else a_pol
        if len(act) == 3 and act[2] > 0 and a_exp[2] <= 0:  # the policy's stop where the expert
            act = a_exp  # drives on would end the episode short of the goal: the expert drives on
        obs, _, term, trunc, info = env.step(np.asarray(act, np.float32))
        done = term or trunc or len(ep["a"]) >= cap
    return ep


def train(cfg: ImitationConfig, out, progress=None, resume: bool = False,
          base: ImitationConfig | None = None) -> dict:
    """Run DAgger for ``cfg.frames`` frames; checkpoints ``out/model.pt`` (every iteration, with the training state),
    ``out/best.pt`` (the best validation SR + SPL so far) and a line per iteration in ``out/log.csv``. ``resume``
    goes on from ``out/model.pt`` with the configuration it was started with (``cfg`` then only sets ``frames`` and
    ``iterations``, which may grow, and ``device``; any other setting in ``cfg`` that is neither its default nor the
    run's own is a ConfigError, not silently dropped; ``base``: the defaults, where the caller's differ from
    :class:`ImitationConfig`'s, as the command line's do)."""
    from sonicverse_core.errors import ConfigError
    from sonicverse_core.tasks import make_env

    if cfg.frames < 1 or cfg.iterations < 1 or cfg.jobs < 1:
        raise ConfigError("--frames, --iterations and --jobs must be >= 1")
    if cfg.head not in ("discrete", "fine", "continuous"):
        raise ConfigError(f"head must be discrete, fine or continuous, got {cfg.head!r}")
    if cfg.agent not in ("av-nav", "savi", "multitask"):
        raise ConfigError(f"agent must be av-nav, savi or multitask, got {cfg.agent!r}")
    if cfg.egomap and cfg.task not in MAP_TASKS:
        raise ConfigError(f"--map is for {', '.join(MAP_TASKS)}")
    if cfg.learner not in ("greedy", "drawn"):
        raise ConfigError(f"learner must be greedy or drawn, got {cfg.learner!r}")
    if cfg.teacher not in ("oracle", "scripted"):
        raise ConfigError(f"teacher must be oracle or scripted, got {cfg.teacher!r}")
    if cfg.route and not (cfg.egomap and cfg.task in ROUTE_TASKS):
        raise ConfigError(f"--map route is for {' and '.join(ROUTE_TASKS)}")
    if cfg.teacher == "scripted" and not (map_kind_for(cfg) in ("follow", "sem", "route2") if cfg.egomap
                                          else cfg.task in ("AudioGoal", "SemanticAudioNav")):
        raise ConfigError("--teacher scripted is for --map on SpeakerFollowing (the scripted follower draws the map) "
                          "or SemanticAudioNav (sem-nav acts on what the semantic map shows), --map route on "
                          "AudioGoal and SemanticAudioNav (sem-nav's route), or without --map on AudioGoal and "
                          "SemanticAudioNav (sem-nav acts on the robot's own sensors)")
    resolve_device(cfg.device)  # an unknown or absent device fails before anything is written
    out = Path(out)
    ck_path = out / "model.pt"
    state, rows, frames, best, start_it = {}, [], 0, None, 0
    if resume:
        if not ck_path.is_file():
            raise ConfigError(f"nothing to resume: {ck_path} does not exist")
        model, meta = load_policy(ck_path)
        state = load_train_state(ck_path)
        if not state:
            raise ConfigError(f"{ck_path} has no training state to resume from")
        old = ImitationConfig(**meta["config"])
        # a setting given that is neither the default nor the run's own would be ignored: refused, not dropped
        base, keep = base or ImitationConfig(), ("frames", "iterations", "device")
        clash = [f"{f.name} {getattr(cfg, f.name)!r} (the run's: {getattr(old, f.name)!r})"
                 for f in fields(ImitationConfig) if f.name not in keep
                 and getattr(cfg, f.name) != getattr(base, f.name) and getattr(cfg, f.name) != getattr(old, f.name)]
        if clash:
            raise ConfigError(f"--resume goes on with the run's own recipe, which these would change: "
                              f"{'; '.join(clash)}. Drop them, or start a new --out")
        cfg = ImitationConfig(**{**asdict(old), "frames": cfg.frames, "iterations": cfg.iterations,
                                 "device": cfg.device})
        rows, frames, best, start_it = meta["log"], state["frames"], state["best"], state["iteration"] + 1
        if start_it >= cfg.iterations:
            raise ConfigError(f"{ck_path} has done {start_it} of {cfg.iterations} iterations: raise --iterations")
    elif ck_path.exists():  # nothing already written is lost
        raise ConfigError(f"{ck_path} exists: choose another --out, or --resume")
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    env = make_env(cfg.task, split="train", sensors=collect_sensors(cfg), width=cfg.size,
                   height=cfg.size, homes=cfg.homes or None)
    spec = env.observation_space["spectrogram"].shape
    adim = env.action_space.shape[0]
    if not resume:
        model = build_policy(cfg, spec, adim)
    model.to(resolve_device(cfg.device))
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)  # (a resumed state is cast to the weights' device)
    if resume:
        opt.load_state_dict(state["optimizer"])
        rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
    data = Dataset(cfg.dataset_frames)
    expert, ego = labellers(cfg, model)
    cap = cfg.rollout_steps or ROLLOUT_STEPS.get(cfg.task, 200)
    val_keys = VAL_KEYS.get(cfg.task, NAV_VAL)
    per_iter = math.ceil(cfg.frames / cfg.iterations)
    log_path = out / "log.csv"
    for i, r in enumerate(rows):  # resumed: the log as far as the checkpoint (a kill may have left a later line)
        append_row(log_path, r, first=i == 0)
    t0 = time.perf_counter() - (rows[-1]["wall_s"] if rows else 0.0)
    if cfg.jobs > 1:
        from agents.dagger_jobs import Jobs
    pool, finished = Jobs(cfg, cfg.jobs) if cfg.jobs > 1 else None, False
    try:
        for it in range(start_it, cfg.iterations):
            if hasattr(model, "stage"):  # SAVi's two stages
                model.stage(1 if it < max(1, round(cfg.stage1 * cfg.iterations)) else 2)
            beta = max(cfg.beta_min, cfg.beta0 * (1 - it / max(cfg.iterations / 2, 1)))
            t_roll = time.perf_counter()
            n = 0
            if pool is not None:  # the jobs collect episodes with this iteration's policy, each its share
                for ep in pool.collect(model, beta, it, per_iter):
                    data.add(ep)
                    n += len(ep["a"])
            while pool is None and n < per_iter:
                ep = run_episode(model, env, expert, ego, cfg, rng, int(rng.integers(2**31)), beta, cap)
                n += len(ep["a"])
                data.add(ep)
            roll_s = time.perf_counter() - t_roll
            frames += n
            t_fit = time.perf_counter()
            model.train()
            parts = []
            for _ in range(cfg.epochs):
                for b in data.batches(rng, cfg.seq, cfg.batch):
                    loss, part = bc_loss(model, b, cfg.aux_weight)
                    opt.zero_grad()
                    loss.backward()
                    torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
                    opt.step()
                    parts.append(part)
            pre = {}
            if getattr(model, "window", None) == 1:  # SAVi's first stage: the goal predictor trained alone too
                pre = pretrain_goal(model, data, rng, cfg.goal_steps)
            model.eval()
            fit_s = time.perf_counter() - t_fit
            val = (evaluate(model, cfg.task, cfg.val_episodes, "val", cfg.size, cfg.seed, pool) if cfg.val_episodes
                   else {})
            row = {"iteration": it, "frames": frames, "beta": round(beta, 3),
                   "loss": round(float(np.mean([q["policy"] for q in parts])), 5),
                   "goal_loss": round(float(np.mean([q.get("goal", np.nan) for q in parts])), 5),
                   "goal_audio_loss": round(float(np.mean([q.get("goal_audio", np.nan) for q in parts])), 5),
                   **{f"{k}_loss": round(float(np.mean([q.get(k, np.nan) for q in parts])), 5)
                      for k in ("category", "occupancy") if k in parts[0]},
                   **({"category_acc_test": pre.get("category_acc_test"), "goal_audio_test": pre.get("goal_audio_test")}
                      if hasattr(model, "stage") else {}),
                   "dataset_frames": data.frames, "rollout_fps": round(n / roll_s, 1),
                   "fit_s": round(fit_s, 2), **{f"val_{k}": val.get(k) for k in val_keys},
                   "wall_s": round(time.perf_counter() - t0, 1)}
            rows.append(row)
            append_row(log_path, row, first=it == 0)
            meta = {"recipe": "dagger", "config": asdict(cfg), "log": rows, "iteration": it}
            if hasattr(model, "window"):  # SAVi: the memory this iteration trained with (1 in the first stage)
                meta["window"] = model.window
            score = sum(v or 0.0 for v in val.values())
            if best is None or score > best:  # the best on validation homes (what is shipped)
                best = score
                save(model, out / "best.pt", meta)
            save(model, ck_path, meta, train_state={  # the latest (to go on from)
                "optimizer": opt.state_dict(), "rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state(),
                "frames": frames, "best": best, "iteration": it})
            if progress is not None:
                progress(row)
        finished = True
    finally:
        env.close()
        if pool is not None:
            pool.close(now=not finished)  # an error or an interruption: the other jobs stop at once
    return {"out": str(out), "checkpoint": str(ck_path), "best": str(out / "best.pt"), "log": rows}
