"""SAVi (Chen et al. 2021, "Semantic Audio-Visual Navigation") and the paper's multi-task model (SAVi + occupancy
anticipation), in torch, with the AV-Nav policy's interface (:class:`agents.models.AVNav`): the same sensors
(depth, binaural spectrogram, odometry pose), the same action heads, the same imitation and PPO recipes.

* **Goal predictor**: its own CNN over the spectrogram, the goal's category (a softmax over the sounding
  categories) and its place from the robot (cosine and sine of its bearing, log(1 + distance)). Trained by
  supervision on the privileged goal (the category and where the goal is) beside the policy.
* **Goal descriptor**: the predictions carried over time in the odometry frame, as SAVi does: while the robot hears
  something, the estimate of where the goal is moves towards each new prediction (``g <- lam g + (1 - lam) pred``,
  the category's probabilities likewise); once the sound has stopped the estimate is kept and moves with the robot
  (SemanticAudioNav's sounds stop). The descriptor the policy reads is that estimate in the robot's current frame
  (bearing, log distance), the category's probabilities and whether anything was heard yet. Its inputs are detached:
  the predictor learns only from its own targets.
* **Scene memory**: each step's observation embedding (depth CNN, audio CNN, pose) is a token; a transformer encoder
  runs over the last ``memory`` tokens of the episode (causal: a token attends to itself and the tokens before it, as
  far back as the window, never across an episode's start; ALiBi's linear recency bias per head), and a decoder
  queried by the current token and the goal descriptor attends to the encoded memory; the actor-critic reads the
  decoder's output.
* **Map** (``map_shape``: ``sonicverse train --map``, as AV-Nav's): an egocentric map (:mod:`agents.maps` names
  which) has its own CNN, whose features join depth, audio and pose in each step's token, so the scene memory holds
  the map as it was at each remembered step.
* **Two stages** (SAVi's): the first third of the imitation runs with a memory of one step (each step sees only
  itself) and trains everything; then the goal predictor is frozen and the memory grows to ``memory`` steps (SAVi
  also freezes the observation encoders: see :meth:`SAVi.stage`).
* **Multi-task** (``occupancy`` = V > 0): a U-Net predicts the occupancy of V x V cells covering 5 m x 5 m in front of
  the camera (visible and unseen cells) from the local occupancy projected from the depth image (points 0.08-1.0 m
  above the floor are obstacles, lower ones free floor), with the policy's state feature tiled and concatenated into
  its last three encoder layers; binary cross-entropy against the scene's own occupancy (cells of the navigability
  grid's floor that are not free), so the occupancy loss shapes the policy's state. The map is an auxiliary task: the
  policy acts on the state feature.

State between calls (``hidden``): one tensor (1, B, S) packing the memory's tokens and which of them are valid, the
goal estimate (odometry x, y), the category's probabilities and whether anything was heard, so the imitation and
PPO loops carry it as they carry the GRU's. A sequence may span episodes (``starts``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from agents.models import DEPTH_MAX, SPEC_MAX, ActorCritic, _cnn, read_checkpoint, write_checkpoint

EXTENT = 5.0  # m: the occupancy window's side (in front of the camera, centred on its axis)
AUDIBLE = 0.002  # mean spectrogram value (log1p |STFT|) above which something is heard (SemanticAudioNav: 0.006-0.03
# while the sound plays, 0 once it and its reverb have stopped)


@dataclass(frozen=True)
class SAViConfig:
    depth_hw: tuple = (64, 64)
    spec_shape: tuple = (2, 64, 49)
    pose_dim: int = 4
    action_dim: int = 2
    hidden: int = 256  # the encoders' width
    d_model: int = 128  # the transformer's width
    memory: int = 32  # steps of scene memory (stage 2)
    layers: int = 2
    heads: int = 4
    n_categories: int = 15  # 0: no category (speaker following)
    lam: float = 0.5  # the goal descriptor's memory per heard step
    primitives: tuple = ()
    aux_goal: bool = True  # the goal predictor's location loss (always on in SAVi)
    occupancy: int = 0  # V: the multi-task model's occupancy map (0: SAVi)
    map_shape: tuple = ()  # (C, H, W) of an egocentric map input (``train --map``), () for none: AVNavConfig's
    map_kind: str = "follow"  # which map (agents.maps): as AVNavConfig's
    hfov: float = 90.0  # the depth camera's (for the projection)
    camera_height: float = 0.55


class SAVi(ActorCritic):
    """See the module's docstring; ``forward`` and :meth:`features` as :class:`agents.models.AVNav`'s."""

    def __init__(self, cfg: SAViConfig = SAViConfig()):
        super().__init__()
        self.cfg = cfg
        h, d = cfg.hidden, cfg.d_model
        self.depth = _cnn(1, cfg.depth_hw, h) if cfg.depth_hw else None
        self.audio = _cnn(cfg.spec_shape[0], cfg.spec_shape[1:], h, k=(5, 3, 3), s=(2, 2, 1))
        # the egocentric map (``--map``; agents.maps): a third CNN, as AV-Nav's, its features part of each token
        self.egomap = _cnn(cfg.map_shape[0], cfg.map_shape[1:], h, k=(4, 3, 3), s=(2, 2, 1)) if cfg.map_shape else None
        self.token = nn.Linear(((2 if cfg.depth_hw else 1) + (1 if cfg.map_shape else 0)) * h + cfg.pose_dim, d)
        # the goal predictor: its own audio encoder (SAVi's is a separate network), the location and category heads
        self.goal_net = _cnn(cfg.spec_shape[0], cfg.spec_shape[1:], h, k=(5, 3, 3), s=(2, 2, 1))
        self.goal_audio = nn.Linear(h, 3)
        self.category = nn.Linear(h, cfg.n_categories) if cfg.n_categories else None
        self.desc_dim = 3 + cfg.n_categories + 1
        layer = nn.TransformerEncoderLayer(d, cfg.heads, 2 * d, dropout=0.0)
        self.encoder = nn.TransformerEncoder(layer, cfg.layers, enable_nested_tensor=False)
        self.query = nn.Linear(d + self.desc_dim, d)
        self.decoder = nn.TransformerDecoderLayer(d, cfg.heads, 2 * d, dropout=0.0)
        self._heads(d, cfg)
        self.goal_head = nn.Linear(d, 3)  # where the goal is, from the state (as AV-Nav's aux head)
        self.window = cfg.memory  # the memory in use (1 in stage 1)
        self.register_buffer("slopes", torch.tensor([2.0 ** (-8.0 * (k + 1) / cfg.heads) for k in range(cfg.heads)]),
                             persistent=False)
        self.occ = OccupancyUNet(cfg.occupancy, d) if cfg.occupancy else None
        # tokens kept between calls: the encoder's layers and the decoder each see a window further back, so
        # stepping one step at a time gives what one call over the whole sequence gives (tested)
        self.kept = max(1, (cfg.layers + 1) * (cfg.memory - 1))
        self._sizes = (self.kept * d, self.kept, 2, cfg.n_categories, 1)

    @property
    def arch(self) -> str:
        """The checkpoint's and the agent's name: ``multitask`` with the occupancy map, else ``savi``."""
        return "multitask" if self.cfg.occupancy else "savi"

    # --- state ------------------------------------------------------------------------------------------------
    def initial_state(self, batch: int) -> torch.Tensor:
        return torch.zeros(1, batch, sum(self._sizes), device=self.device)

    def _unpack(self, h):
        B = h.shape[1]
        mem, valid, est, cat, have = torch.split(h[0], self._sizes, dim=1)
        return mem.reshape(B, self.kept, self.cfg.d_model).transpose(0, 1), valid.T > 0.5, est, cat, have

    def _pack(self, mem, valid, est, cat, have):
        B = mem.shape[1]
        return torch.cat([mem.transpose(0, 1).reshape(B, -1), valid.T.float(), est, cat, have], 1)[None]

    # --- the model --------------------------------------------------------------------------------------------
    def encode(self, depth, spec, pose, egomap=None):
        """(observation tokens (T, B, d), the goal predictor's audio features (T, B, H)); ``egomap`` (T, B, C, H, W)
        in [0, 1], the map input of a model with ``cfg.map_shape``."""
        T, B = spec.shape[:2]
        x = (spec.reshape(T * B, *spec.shape[2:]).float() / SPEC_MAX).clamp(0, 1)
        parts = [self.audio(x), pose.reshape(T * B, -1).float()]
        if self.depth is not None:
            d = (depth.reshape(T * B, *depth.shape[2:]).permute(0, 3, 1, 2).float() / DEPTH_MAX).clamp(0, 1)
            parts.insert(0, self.depth(d))
        if self.egomap is not None:
            if egomap is None:
                raise ValueError("this policy reads an egocentric map: give egomap")
            parts.append(self.egomap(egomap.reshape(T * B, *egomap.shape[2:]).float()))
        return self.token(torch.cat(parts, 1)).reshape(T, B, -1), self.goal_net(x).reshape(T, B, -1)

    def descriptor(self, a, spec, pose, est, cat, have, starts):
        """The goal descriptor per step (T, B, desc_dim) and the carried estimate (see the module's docstring)."""
        T = a.shape[0]
        with torch.no_grad():
            loc = self.goal_audio(a)
            b = torch.atan2(loc[..., 1], loc[..., 0])
            dist = torch.expm1(loc[..., 2].clamp(0.0, 3.0))
            probs = torch.softmax(self.category(a), -1) if self.category is not None else a[..., :0]
            heard = spec.float().mean(dim=(2, 3, 4)) > AUDIBLE  # (T, B)
            px, py = pose[..., 0].float(), pose[..., 1].float()
            yaw = torch.atan2(pose[..., 2].float(), pose[..., 3].float())
            out = []
            lam = self.cfg.lam
            for t in range(T):
                keep = (1.0 - starts[t].float())[:, None]
                est, cat, have = est * keep, cat * keep, have * keep
                gx = px[t] + dist[t] * torch.cos(yaw[t] + b[t])
                gy = py[t] + dist[t] * torch.sin(yaw[t] + b[t])
                pred = torch.stack([gx, gy], 1)
                w = torch.where(have > 0, torch.full_like(have, lam), torch.zeros_like(have))  # the first: as is
                hd = heard[t][:, None].float()
                est = hd * (w * est + (1 - w) * pred) + (1 - hd) * est
                if cat.shape[1]:
                    cat = hd * (w * cat + (1 - w) * probs[t]) + (1 - hd) * cat
                have = torch.maximum(have, hd)
                rx, ry = est[:, 0] - px[t], est[:, 1] - py[t]
                rb = torch.atan2(ry, rx) - yaw[t]
                rel = torch.stack([torch.cos(rb), torch.sin(rb), torch.log1p(torch.hypot(rx, ry))], 1) * have
                out.append(torch.cat([rel, cat, have], 1))
        return torch.stack(out), est, cat, have

    def features(self, depth, spec, pose, hidden, starts, egomap=None):
        """(state features (T, B, d), audio features (T, B, H), the next state)."""
        x, a = self.encode(depth, spec, pose, egomap)
        T, B, d = x.shape
        mem, valid, est, cat, have = self._unpack(hidden)
        starts = starts.float()
        desc, est, cat, have = self.descriptor(a, spec, pose, est, cat, have, starts)
        # tokens: [memory (M), new (T)]; episode index per token (memory 0; +1 at each start among the new ones)
        ep_new = torch.cumsum(starts, 0)  # (T, B)
        M = mem.shape[0] if bool(valid.any()) else 0
        dev = x.device
        tokens, ep, ok = x, ep_new, torch.ones(T, B, dtype=torch.bool, device=dev)
        if M:
            tokens = torch.cat([mem, x], 0)
            ep = torch.cat([torch.zeros(M, B, device=dev), ep_new], 0)
            ok = torch.cat([valid, ok], 0)
        L = tokens.shape[0]
        i = torch.arange(L, device=dev)
        near = (i[None, :] <= i[:, None]) & (i[:, None] - i[None, :] < self.window)  # (L, L): causal, a window
        allow = near[None] & (ep.T[:, :, None] == ep.T[:, None, :]) & ok.T[:, None, :]  # (B, L, L)
        allow = allow | torch.eye(L, dtype=torch.bool, device=dev)[None]  # a token always sees itself
        # ALiBi (Press et al. 2022): each head's attention falls off linearly with a token's age, at its own slope,
        # so the current step stands out in a bag of tokens with no positions
        age = (i[:, None] - i[None, :]).clamp(min=0).float()
        bias = -self.slopes[None, :, None, None] * age  # (1, heads, L, L)
        mask = torch.where(allow[:, None], bias, float("-inf")).reshape(B * self.cfg.heads, L, L)
        enc = self.encoder(tokens, mask=mask)
        q = self.query(torch.cat([x, desc], -1))
        self_only = torch.where(torch.eye(T, dtype=torch.bool, device=dev), 0.0, float("-inf"))
        y = self.decoder(q, enc, tgt_mask=self_only, memory_mask=mask[:, -T:, :])
        # the next state: the last ``memory`` tokens of the episode the sequence ends in (earlier ones invalid)
        last = ep_new[-1:]
        keep = torch.cat([valid & (last == 0), ep_new == last], 0)[-self.kept:]
        toks = torch.cat([mem, x], 0)[-self.kept:].detach()
        nxt = self._pack(toks, keep, est, cat, have)
        return y, a, nxt

    # --- training helpers -------------------------------------------------------------------------------------
    def extra_loss(self, b: dict, y, a, m) -> tuple[torch.Tensor, dict]:
        """The goal predictor's category loss (``c``: the goal's category index) and the occupancy loss (``o``:
        the true occupancy, V x V uint8) on a batch, masked by ``m``."""
        loss, parts = torch.zeros((), device=m.device), {}
        if self.category is not None and "c" in b:
            ce = nn.functional.cross_entropy(self.category(a).reshape(-1, self.cfg.n_categories),
                                             b["c"].reshape(-1).long(), reduction="none").reshape(m.shape)
            cl = (ce * m).sum() / m.sum()
            parts["category"] = float(cl.detach())
            loss = loss + cl
        if self.occ is not None and "o" in b:
            T, B = m.shape
            depth = b["d"].float() * (DEPTH_MAX / 255)
            local = project_depth(depth.reshape(T * B, *depth.shape[2:]), self.cfg.occupancy, self.cfg.hfov,
                                  self.cfg.camera_height)
            logits = self.occ(local, y.reshape(T * B, -1))
            bce = nn.functional.binary_cross_entropy_with_logits(
                logits, b["o"].reshape(T * B, *logits.shape[1:]).float(), reduction="none").mean((1, 2))
            ol = (bce * m.reshape(-1)).sum() / m.sum()
            parts["occupancy"] = float(ol.detach())
            loss = loss + ol
        return loss, parts

    def stage(self, k: int) -> None:
        """SAVi's stages: 1, a memory of one step, everything trains; 2, the full memory, the goal predictor
        frozen. (SAVi also freezes the observation encoders. Here, freezing them after 8k frames of AudioGoal while the
        memory grew from 1 to 32 steps, with no recency bias, raised the policy loss from 1.11 to 1.32 and took
        validation SR from 0.25 to 0-0.125; the encoders now keep training and attention has a recency bias.)"""
        self.window = 1 if k == 1 else self.cfg.memory
        frozen = [self.goal_net, self.goal_audio] + ([self.category] if self.category is not None else [])
        for mod in frozen:
            for p in mod.parameters():
                p.requires_grad_(k == 1)


class OccupancyUNet(nn.Module):
    """The multi-task model's occupancy anticipation: (N, 2, V, V) local occupancy (obstacle, seen) and the state
    feature (N, d) -> logits (N, V, V); the state is tiled into the last three encoder layers."""

    def __init__(self, V: int, d: int, ch: int = 16, state: int = 32):
        super().__init__()
        if V < 16 or V % 8:
            raise ValueError(f"occupancy V must be a multiple of 8 and >= 16, got {V}")
        self.state = nn.Linear(d, state)
        c = (ch, 2 * ch, 4 * ch, 4 * ch)
        self.e0 = _block(2, c[0])
        self.e1 = _block(c[0] + state, c[1])
        self.e2 = _block(c[1] + state, c[2])
        self.e3 = _block(c[2] + state, c[3])
        self.d2 = _block(c[3] + c[2], c[2])
        self.d1 = _block(c[2] + c[1], c[1])
        self.d0 = _block(c[1] + c[0], c[0])
        self.out = nn.Conv2d(c[0], 1, 1)
        self.pool = nn.MaxPool2d(2)
        self.up = nn.Upsample(scale_factor=2, mode="nearest")

    def forward(self, local, feat):
        s = torch.relu(self.state(feat))[:, :, None, None]

        def tile(x):
            return torch.cat([x, s.expand(-1, -1, x.shape[2], x.shape[3])], 1)

        x0 = self.e0(local)
        x1 = self.e1(tile(self.pool(x0)))
        x2 = self.e2(tile(self.pool(x1)))
        x3 = self.e3(tile(self.pool(x2)))
        y = self.d2(torch.cat([self.up(x3), x2], 1))
        y = self.d1(torch.cat([self.up(y), x1], 1))
        y = self.d0(torch.cat([self.up(y), x0], 1))
        return self.out(y)[:, 0]


def _block(i: int, o: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(i, o, 3, padding=1), nn.ReLU(), nn.Conv2d(o, o, 3, padding=1), nn.ReLU())


def project_depth(depth: torch.Tensor, V: int, hfov: float, camera_height: float, stride: int = 2) -> torch.Tensor:
    """(N, 2, V, V): the depth images' (N, H, W, 1 or N, H, W; metres) points in the V x V window of ``EXTENT`` m in
    front of the camera (row: distance ahead, 0 nearest; column: from the left edge), as obstacle (0.08-1.0 m above
    the floor) and seen (any point) indicators."""
    if depth.dim() == 4:
        depth = depth[..., 0]
    N, H, W = depth.shape
    z = depth[:, ::stride, ::stride]
    fx = (W / 2) / math.tan(math.radians(hfov) / 2)
    dev = depth.device
    cols = torch.arange(0, W, stride, dtype=torch.float32, device=dev)
    rows = torch.arange(0, H, stride, dtype=torch.float32, device=dev)
    u = ((cols - W / 2 + 0.5) / fx)[None, None, :]
    v = ((rows - H / 2 + 0.5) / fx)[None, :, None]
    left, height = -u * z, camera_height - v * z
    cell = EXTENT / V
    i = torch.floor(z / cell).long()
    j = torch.floor((EXTENT / 2 - left) / cell).long()
    inside = (z > 0.1) & (z < DEPTH_MAX - 1e-3) & (i >= 0) & (i < V) & (j >= 0) & (j < V)
    obst = inside & (height > 0.08) & (height < 1.0)
    n = torch.arange(N, device=dev)[:, None, None].expand_as(i)
    flat = (n * V * V + i.clamp(0, V - 1) * V + j.clamp(0, V - 1))
    out = torch.zeros(2, N * V * V, device=dev)
    out[0].index_add_(0, flat[obst], torch.ones(int(obst.sum()), device=dev))
    out[1].index_add_(0, flat[inside], torch.ones(int(inside.sum()), device=dev))
    return (out.reshape(2, N, V, V).permute(1, 0, 2, 3) > 0).float()


def true_occupancy(world, V: int) -> np.ndarray:
    """(V, V) uint8: 1 where the cell of the window in front of the robot's camera (as :func:`project_depth`'s) is
    not free floor in the scene's navigability grid (or outside it)."""
    g = world.grid
    x, y, yaw = world.pose
    cell = EXTENT / V
    f = (np.arange(V) + 0.5) * cell
    left = EXTENT / 2 - (np.arange(V) + 0.5) * cell
    F, Lf = np.meshgrid(f, left, indexing="ij")
    from agents.scripted import window_cells

    _, _, r, c, inside = window_cells(g, x, y, yaw, F, Lf)
    free = g.floor[r, c] & inside
    return (~free).reshape(V, V).astype(np.uint8)


def save(model: SAVi, path, meta: dict, half: bool = False, train_state: dict | None = None) -> None:
    write_checkpoint(model, model.arch, path, meta, half, train_state)


def load(path, arch: str = "savi") -> tuple[SAVi, dict]:
    """The model acts with the memory it was trained with (``meta["window"]``: 1 for a first-stage checkpoint)."""
    names = {"savi": "SAVi checkpoint", "multitask": "multi-task checkpoint"}
    model, meta = read_checkpoint(path, arch, lambda c: SAVi(SAViConfig(**c)), names[arch])
    model.window = int(meta.get("window", model.cfg.memory))
    return model, meta
