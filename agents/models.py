"""Learned policies in torch (on the CPU by default; on CUDA with ``--device cuda`` or ``auto``: :func:`resolve_device`).

:class:`AVNav`: the audio-visual navigation policy of SoundSpaces (Chen et al. 2020): a CNN over the depth image, a
CNN over the binaural spectrogram, the odometry pose, a GRU over time, and an actor-critic head. The action is the
TurtleBot's two wheel velocities in [-1, 1] (plus a stop output on tasks that have one), from one of two heads:

* ``continuous``: a Gaussian whose mean is squashed by tanh, with a learned log standard deviation (used by PPO;
  imitation and evaluation use the mean);
* ``discrete`` (``AVNavConfig.primitives``): a categorical over a fixed set of wheel-velocity pairs (straight ahead
  at three speeds, veering at four strengths each way, turning on the spot at two rates each way, standing still;
  plus a stop on tasks that have one). Behaviour cloning fits it with cross-entropy, so where the expert turns left
  in some states and right in similar ones the policy picks one, where the continuous head's mean averages them into
  driving straight on.

With ``aux_goal`` the model also predicts where the goal is from the robot (cosine and sine of its bearing,
log(1 + distance)): from the GRU's state (what it has heard and seen so far) and from the current spectrogram alone.
These heads are trained beside the policy on the privileged goal position (an auxiliary loss, as SAVi's goal
predictor) and are not used to act.

With ``map_shape`` (``sonicverse train --map``) a third CNN reads an egocentric map whose features join the GRU's
input: on speaker following (``map_kind`` "follow") :class:`agents.following.EgoMap` (the floor plan, a belief of
where the person is from the robot's own ears and camera, who the camera saw, the route the scripted follower would
take); on AudioGoal ("nav") :class:`agents.navmap.NavEgoMap` (what the robot mapped itself: obstacles and floor
from depth, how loud the sound was where it stood, its track); on SemanticAudioNav ("sem")
:class:`agents.navmap.SemNavMap` (that, and where the semantic camera saw the category the robot's ears name).
"""
from __future__ import annotations

import contextlib
from dataclasses import asdict, dataclass

import torch
from torch import nn

DEPTH_MAX = 10.0
SPEC_MAX = 20.0


@dataclass(frozen=True)
class AVNavConfig:
    depth_hw: tuple = (64, 64)
    spec_shape: tuple = (2, 64, 49)
    pose_dim: int = 4
    action_dim: int = 2
    hidden: int = 256
    primitives: tuple = ()  # () : the continuous head; else the discrete head's wheel-velocity pairs (+ stop)
    aux_goal: bool = False  # the goal-prediction heads (auxiliary loss)
    map_shape: tuple = ()  # (C, H, W) of an egocentric map input, () for none
    map_kind: str = "follow"  # which map: "follow" agents.following.EgoMap, "nav" agents.navmap.NavEgoMap, "sem"
    # agents.navmap.SemNavMap


def primitives_for(action_dim: int, fine: bool = False) -> tuple:
    """The discrete head's actions in wheel-velocity units: straight ahead at full, half and quarter speed, veering
    (the inner wheel at 0.75 .. 0 of the outer), turning on the spot at half and a quarter of full speed, standing
    still; with a stop component (action_dim 3) its stop (+1) and, on every other action, -1. The shortest-path
    expert's actions lie within 0.13 of one of them (its turns on the spot run at the robot's turn-rate limit, 0.52:
    tested). ``fine`` (``--head fine``): 25 pairs, straight ahead at three quarters too and veering every 0.125
    (0.875 .. 0); the scripted follower snapped to them keeps more of its time in band than snapped to the 16
    (README, "Why it stays below its teacher")."""
    pairs = [(1.0, 1.0), (0.75, 0.75), (0.5, 0.5), (0.25, 0.25)] if fine else [(1.0, 1.0), (0.5, 0.5), (0.25, 0.25)]
    for r in (0.875, 0.75, 0.625, 0.5, 0.375, 0.25, 0.125, 0.0) if fine else (0.75, 0.5, 0.25, 0.0):
        pairs += [(r, 1.0), (1.0, r)]
    pairs += [(-0.5, 0.5), (0.5, -0.5), (-0.25, 0.25), (0.25, -0.25), (0.0, 0.0)]
    if action_dim == 2:
        return tuple(pairs)
    if action_dim == 3:
        return tuple((l, r, -1.0) for l, r in pairs) + ((0.0, 0.0, 1.0),)
    raise ValueError(f"no discrete actions for action_dim {action_dim}")


def head_primitives(head: str, action_dim: int) -> tuple:
    """``AVNavConfig.primitives`` for ``--head``: the 16 pairs (discrete), the 25 (fine), none (continuous)."""
    return () if head == "continuous" else primitives_for(action_dim, fine=head == "fine")


DEVICES = ("cpu", "cuda", "auto")


def resolve_device(name: str | None = "cpu") -> torch.device:
    """The torch device ``--device`` names: ``cpu`` (the default), ``cuda`` (a ConfigError where torch sees no
    CUDA device) or ``auto`` (CUDA when present, else the CPU)."""
    from sonicverse_core.errors import ConfigError

    name = name or "cpu"
    if name not in DEVICES:
        raise ConfigError(f"device must be one of {', '.join(DEVICES)}, got {name!r}")
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda: torch sees no CUDA device here (torch "
                          f"{torch.__version__}, CUDA build {torch.version.cuda}); use --device cpu or auto")
    return torch.device(name)


@contextlib.contextmanager
def acting_threads(n: int = 1):
    """Torch on ``n`` threads inside the block. Acting runs the model on a batch of one between environment steps;
    with torch's default threads its OpenMP workers spin after every step and take the cores from the renderer
    (`sonicverse bench train`: the env's step 1.36 -> 2.49 ms, rollouts 420 -> 286 frames/s on 2 cores)."""
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def _cnn(in_ch: int, hw: tuple, out: int, k=(8, 4, 3), s=(4, 2, 1)) -> nn.Sequential:
    layers, ch, h, w = [], in_ch, hw[0], hw[1]
    for kk, ss, oc in zip(k, s, (32, 64, 64)):
        layers += [nn.Conv2d(ch, oc, kk, ss), nn.ReLU()]
        ch, h, w = oc, (h - kk) // ss + 1, (w - kk) // ss + 1
    if h < 1 or w < 1:
        raise ValueError(f"input {hw} too small for the encoder")
    return nn.Sequential(*layers, nn.Flatten(), nn.Linear(ch * h * w, out), nn.ReLU())


class ActorCritic(nn.Module):
    """What every learned policy shares: the action head (continuous or discrete, ``cfg.primitives``), the critic,
    ``forward`` from the subclass's ``features`` and :meth:`act` / :meth:`label`."""

    def _heads(self, width: int, cfg) -> None:
        self.discrete = len(cfg.primitives) > 0
        self.actor = nn.Linear(width, len(cfg.primitives) if self.discrete else cfg.action_dim)
        self.critic = nn.Linear(width, 1)
        if self.discrete:
            self.register_buffer("table", torch.tensor(cfg.primitives, dtype=torch.float32), persistent=False)
        else:
            self.log_std = nn.Parameter(torch.full((cfg.action_dim,), -0.5))

    @property
    def device(self) -> torch.device:
        """Where the weights are (inputs go there; :func:`resolve_device`)."""
        return self.actor.weight.device

    def head(self, y) -> torch.Tensor:
        return self.actor(y) if self.discrete else torch.tanh(self.actor(y))

    def forward(self, depth, spec, pose, hidden, starts, egomap=None):
        kw = {} if egomap is None else {"egomap": egomap}
        y, _, hidden = self.features(depth, spec, pose, hidden, starts, **kw)
        return self.head(y), self.critic(y).squeeze(-1), hidden

    def act(self, out: torch.Tensor) -> torch.Tensor:
        """Wheel velocities (+ stop) from :meth:`forward`'s action output: the mean, or the most likely primitive."""
        return self.table[out.argmax(-1)] if self.discrete else out

    def label(self, actions: torch.Tensor) -> torch.Tensor:
        """The discrete head's class for each action: the nearest primitive."""
        return torch.cdist(actions.reshape(-1, actions.shape[-1]).float(), self.table).argmin(-1).reshape(
            actions.shape[:-1])


class AVNav(ActorCritic):
    """``forward(depth (T, B, H, W, 1), spec (T, B, 2, F, W), pose (T, B, 4), hidden (1, B, H), starts (T, B))`` ->
    (action (T, B, A), value (T, B), hidden): the mean in [-1, 1] (continuous head) or the logits over
    ``cfg.primitives`` (discrete head); :meth:`act` turns either into wheel velocities. ``starts`` marks each
    episode's first step: the GRU's state is zeroed there."""

    arch = "av-nav"  # the checkpoint's and the agent's name (as SAVi.arch)

    def __init__(self, cfg: AVNavConfig = AVNavConfig()):
        super().__init__()
        self.cfg = cfg
        h = cfg.hidden
        self.depth = _cnn(1, cfg.depth_hw, h) if cfg.depth_hw else None  # () : an audio-only policy
        self.audio = _cnn(cfg.spec_shape[0], cfg.spec_shape[1:], h, k=(5, 3, 3), s=(2, 2, 1))
        # the egocentric map (EgoMap): floor, belief, sightings, route
        self.egomap = _cnn(cfg.map_shape[0], cfg.map_shape[1:], h, k=(4, 3, 3), s=(2, 2, 1)) if cfg.map_shape else None
        self.gru = nn.GRU(((2 if cfg.depth_hw else 1) + (1 if cfg.map_shape else 0)) * h + cfg.pose_dim, h)
        self._heads(h, cfg)
        if cfg.aux_goal:
            self.goal_head = nn.Linear(h, 3)  # from the GRU's state
            self.goal_audio = nn.Linear(h, 3)  # from the current spectrogram alone

    def initial_state(self, batch: int) -> torch.Tensor:
        return torch.zeros(1, batch, self.cfg.hidden, device=self.device)

    def encode(self, depth, spec, pose, egomap=None) -> tuple[torch.Tensor, torch.Tensor]:
        """``depth`` may be None for an audio-only policy; ``egomap`` (T, B, C, H, W) in [0, 1], the map input of a
        policy with ``cfg.map_shape``."""
        T, B = spec.shape[:2]
        a = self.audio((spec.reshape(T * B, *spec.shape[2:]).float() / SPEC_MAX).clamp(0, 1))
        parts = [a, pose.reshape(T * B, -1).float()]
        if self.depth is not None:
            d = (depth.reshape(T * B, *depth.shape[2:]).permute(0, 3, 1, 2).float() / DEPTH_MAX).clamp(0, 1)
            parts.insert(0, self.depth(d))
        if self.egomap is not None:
            if egomap is None:
                raise ValueError("this policy reads an egocentric map: give egomap")
            parts.append(self.egomap(egomap.reshape(T * B, *egomap.shape[2:]).float()))
        return torch.cat(parts, 1).reshape(T, B, -1), a.reshape(T, B, -1)

    def features(self, depth, spec, pose, hidden, starts, egomap=None):
        """(GRU outputs (T, B, H), audio features (T, B, H), the last hidden state)."""
        x, a = self.encode(depth, spec, pose, egomap)
        starts = starts.float()
        if x.shape[0] == 1 or not bool(starts[1:].any()):  # no episode starts inside: one call over the sequence
            y, hidden = self.gru(x, hidden * (1.0 - starts[0]).view(1, -1, 1))
            return y, a, hidden
        outs = []
        for t in range(x.shape[0]):  # reset the state at episode starts (sequences may span episodes)
            hidden = hidden * (1.0 - starts[t]).view(1, -1, 1)
            o, hidden = self.gru(x[t:t + 1], hidden)
            outs.append(o)
        return torch.cat(outs, 0), a, hidden


def write_checkpoint(model: nn.Module, arch: str, path, meta: dict, half: bool = False,
                     train_state: dict | None = None) -> None:
    """Write ``model`` (with a dataclass ``cfg``) atomically; ``half`` stores the weights as float16 (half the size,
    for shipping; they load back as float32); ``train_state`` (optimizer, random states, counters) is what
    ``--resume`` goes on from."""
    from sonicverse_core.storage import atomic_write

    state = {k: (v.half() if half and v.is_floating_point() else v).detach().cpu()
             for k, v in model.state_dict().items()}  # CPU tensors: a checkpoint loads anywhere
    ck = {"arch": arch, "config": asdict(model.cfg), "state": state, "meta": meta}
    if train_state is not None:
        ck["train_state"] = train_state
    with atomic_write(path) as f:
        torch.save(ck, f)


def read_checkpoint(path, arch: str, build, what: str) -> tuple[nn.Module, dict]:
    """(model in eval mode, meta) from a file :func:`write_checkpoint` wrote for ``arch``; ``build(config dict)``
    makes the empty model. A missing, damaged or foreign file is a ConfigError naming ``what`` it should be."""
    from pathlib import Path

    from sonicverse_core.errors import ConfigError

    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{what} not found: {p}")
    try:
        ck = torch.load(p, map_location="cpu", weights_only=False)
        if ck.get("arch") != arch:
            raise ValueError(f"arch {ck.get('arch')!r}")
        model = build({k: _tuples(v) for k, v in ck["config"].items()})
        model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in ck["state"].items()})
    except Exception as exc:  # a damaged or foreign file: one clear line
        raise ConfigError(f"{p} is not a Sonicverse {what} ({type(exc).__name__}: {exc})") from None
    model.eval()
    return model, ck.get("meta", {})


def save(model: AVNav, path, meta: dict, half: bool = False, train_state: dict | None = None) -> None:
    """An AV-Nav checkpoint (:func:`write_checkpoint`)."""
    write_checkpoint(model, "av-nav", path, meta, half, train_state)


def load_train_state(path) -> dict:
    """The training state saved beside a checkpoint's weights (``{}`` when it has none)."""
    return torch.load(path, map_location="cpu", weights_only=False).get("train_state", {})


def _tuples(v):
    return tuple(_tuples(x) for x in v) if isinstance(v, (list, tuple)) else v


def load(path) -> tuple[AVNav, dict]:
    return read_checkpoint(path, "av-nav", lambda c: AVNav(AVNavConfig(**c)), "AV-Nav checkpoint")


POLICIES = ("av-nav", "savi", "multitask")  # the learned policies' architectures (checkpoints' "arch")


class PolicyEnsemble(nn.Module):
    """Several AV-Nav policies with one configuration (sensors, map, discrete actions) acting as one: each keeps its
    own recurrent state, and the ensemble's action distribution is the mean of theirs (its output is the log of that
    mean, so a softmax of it, or its argmax, is what :func:`agents.imitation._policy_step` reads). For acting only:
    it does not train. Session 34's ensembles of the teacher-only recipe did not pay (on the 30 test episodes of
    speaker following, two members kept the band 0.749 of the time and three 0.695, against 0.734 and 0.715 alone,
    all within the noise); session 36's two seeds trained with ``--learner drawn`` ship as the speaker follower
    (0.756; its better member alone 0.746 on the sound before), and from session 38 to 44 the AudioGoal policy was two
    imitation runs joined (41.0% SR over 200 test episodes against 36.0% and 37.0% alone; README, "Learned
    agents"; now ``av-nav_AudioGoal_oracle.pt``)."""

    arch = "ensemble"

    def __init__(self, members: list):
        super().__init__()
        from sonicverse_core.errors import ConfigError

        if len(members) < 2:
            raise ConfigError("an ensemble needs two policies or more")
        cfg = members[0].cfg
        for m in members:
            if not isinstance(m, AVNav) or not m.discrete:
                raise ConfigError("an ensemble's members are AV-Nav policies with the discrete head")
            if _acting(m.cfg) != _acting(cfg):
                raise ConfigError("an ensemble's members must share one configuration (sensors, map, actions): "
                                  f"{_config_diff(_acting(cfg), _acting(m.cfg))}")
        self.members = nn.ModuleList(members)
        self.cfg = cfg
        self.discrete = True
        self.register_buffer("table", members[0].table.clone(), persistent=False)

    @property
    def device(self) -> torch.device:
        return self.members[0].device

    def initial_state(self, batch: int) -> torch.Tensor:
        """The members' states stacked: (members, layers, batch, hidden)."""
        return torch.stack([m.initial_state(batch) for m in self.members])

    def forward(self, depth, spec, pose, hidden, starts, egomap=None):
        probs, values, states = [], [], []
        for m, h in zip(self.members, hidden):
            out, v, h = m(depth, spec, pose, h, starts, egomap=egomap)
            probs.append(torch.softmax(out.float(), -1))
            values.append(v)
            states.append(h)
        p = torch.stack(probs).mean(0)
        return torch.log(p.clamp_min(1e-12)), torch.stack(values).mean(0), torch.stack(states)

    def act(self, out: torch.Tensor) -> torch.Tensor:
        """The most likely primitive of the mean distribution."""
        return self.table[out.argmax(-1)]


def _acting(cfg) -> dict:
    """An AV-Nav configuration as it bears on acting: which map a policy without a map input would read means
    nothing (files from before ``map_kind`` existed hold its default, "follow"; later ones the task's)."""
    d = asdict(cfg)
    if not d.get("map_shape"):
        d.pop("map_kind", None)
    return d


def _config_diff(a: dict, b: dict) -> str:
    return ", ".join(f"{k} {a.get(k)!r} vs {b.get(k)!r}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k))


def write_ensemble(paths, out, half: bool = True, task: str | None = None, temperature: float = 1.0) -> dict:
    """One checkpoint holding the policies in ``paths`` (AV-Nav checkpoints trained on one task, ``task`` when
    given, with one configuration) as a :class:`PolicyEnsemble`; ``half`` stores float16 weights; ``temperature``
    (in its meta): the player draws from the mean distribution raised to 1 / temperature (1: as it is; below 1,
    nearer the most likely action). Returns its meta."""
    from pathlib import Path

    from sonicverse_core.errors import ConfigError
    from sonicverse_core.storage import atomic_write

    for p in paths:
        if Path(p).is_file() and _file_arch(p) == "ensemble":
            raise ConfigError(f"{p} is an ensemble already: join its members' own checkpoints")
    models, metas = zip(*(load(p) for p in paths))
    PolicyEnsemble(list(models))  # the members agree (one configuration, discrete heads), or a ConfigError says why
    tasks = {(mt.get("config") or {}).get("task") for mt in metas}
    if len(tasks) > 1:
        raise ConfigError(f"an ensemble's members are trained on one task, not {sorted(map(str, tasks))}")
    if task is not None and tasks != {task}:
        raise ConfigError(f"the checkpoints were trained on {tasks.pop()}, not {task}")
    members = []
    for m, mt in zip(models, metas):
        state = {k: (v.half() if half and v.is_floating_point() else v).detach().cpu()
                 for k, v in m.state_dict().items()}
        members.append({"arch": "av-nav", "config": asdict(m.cfg), "state": state, "meta": mt})
    if not 0.05 <= temperature <= 10.0:
        raise ConfigError(f"temperature {temperature}: give 0.05 to 10")
    meta = {"recipe": "ensemble", "config": {"task": tasks.pop()}, "temperature": float(temperature),
            "members": [{"source": str(Path(p)), "seed": (mt.get("config") or {}).get("seed"),
                         "iteration": mt.get("iteration")} for p, mt in zip(paths, metas)]}
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out) as f:
        torch.save({"arch": "ensemble", "members": members, "meta": meta}, f)
    return meta


def load_ensemble(path) -> tuple[PolicyEnsemble, dict]:
    """(:class:`PolicyEnsemble` in eval mode, meta) from a file :func:`write_ensemble` wrote."""
    ens, ck = _read_ensemble(path)
    return ens, ck.get("meta", {})


def _read_ensemble(path) -> tuple[PolicyEnsemble, dict]:
    """(:class:`PolicyEnsemble` in eval mode, the file's whole content) of a file :func:`write_ensemble` wrote; a
    missing, damaged or foreign file is a ConfigError."""
    from pathlib import Path

    from sonicverse_core.errors import ConfigError

    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"policy ensemble not found: {p}")
    try:
        ck = torch.load(p, map_location="cpu", weights_only=False)
        if ck.get("arch") != "ensemble":
            raise ValueError(f"arch {ck.get('arch')!r}")
        models = []
        for m in ck["members"]:
            model = AVNav(AVNavConfig(**{k: _tuples(v) for k, v in m["config"].items()}))
            model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in m["state"].items()})
            models.append(model)
    except Exception as exc:  # a damaged or foreign file: one clear line
        raise ConfigError(f"{p} is not a Sonicverse policy ensemble ({type(exc).__name__}: {exc})") from None
    ens = PolicyEnsemble(models)
    ens.eval()
    return ens, ck


def unpack_ensemble(path, out_dir) -> list[str]:
    """Each member of the ensemble in ``path`` as a checkpoint of its own, ``out_dir/member{k}.pt`` (its weights
    as the ensemble stores them, its own training meta): what PPO fine-tunes, or another ensemble joins. Refuses a
    file that is not an ensemble and members that exist already. Returns the paths written."""
    from pathlib import Path

    from sonicverse_core.errors import ConfigError
    from sonicverse_core.storage import atomic_write

    members = _read_ensemble(path)[1]["members"]  # a missing, damaged or foreign file: one clear line
    out = [Path(out_dir) / f"member{k}.pt" for k in range(len(members))]
    for q in out:
        if q.exists():
            raise ConfigError(f"{q} exists: give another --out")
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    for m, q in zip(members, out):
        with atomic_write(q) as f:
            torch.save({"arch": m["arch"], "config": m["config"], "state": m["state"], "meta": m.get("meta", {})}, f)
    return [str(q) for q in out]


def _file_arch(path) -> str | None:
    """The checkpoint's "arch", read without loading its tensors (memory-mapped)."""
    try:
        return torch.load(path, map_location="cpu", weights_only=False, mmap=True).get("arch")
    except Exception:
        return None  # read_checkpoint names the problem


def load_policy(path, arch: str | None = None):
    """(model, meta) of any learned policy's checkpoint (``arch``: the one expected, else whichever it holds); an
    ensemble of ``av-nav`` policies (:func:`write_ensemble`) loads where ``av-nav`` is expected."""
    from sonicverse_core.errors import ConfigError

    if _file_arch(path) == "ensemble" and arch in (None, "av-nav"):
        return load_ensemble(path)
    if arch is None:
        arch = _file_arch(path)
        arch = arch if arch in POLICIES else "av-nav"
    if arch == "av-nav":
        return load(path)
    if arch in ("savi", "multitask"):
        from agents.savi import load as load_savi

        return load_savi(path, arch)
    raise ConfigError(f"unknown policy architecture '{arch}'; use one of {', '.join(POLICIES)}")


def save_policy(model, path, meta: dict, half: bool = False, train_state: dict | None = None) -> None:
    """A checkpoint of any learned policy (its ``arch``: ``av-nav`` unless the model says otherwise)."""
    write_checkpoint(model, getattr(model, "arch", "av-nav"), path, meta, half, train_state)
