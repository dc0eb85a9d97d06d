"""Learned agents (agents/models.py, agents/imitation.py, agents/learned.py): the AV-Nav policy's shapes and its GRU
reset at episode starts, behaviour cloning that fits the expert, a short DAgger run end to end (checkpoint, log,
evaluation through the harness), the `module:callable` hook, and clear errors for bad checkpoints."""
import csv
import json

import numpy as np
import pytest
import torch

from agents.imitation import Dataset, ImitationConfig, train
from agents.models import AVNav, AVNavConfig, load, save


def _batch(T, B, cfg):
    g = torch.Generator().manual_seed(0)
    return (torch.rand(T, B, *cfg.depth_hw, 1, generator=g) * 10, torch.rand(T, B, *cfg.spec_shape, generator=g) * 5,
            torch.rand(T, B, cfg.pose_dim, generator=g))


def test_policy_shapes_bounds_and_the_gru_restarting_at_episode_starts():
    cfg = AVNavConfig()
    m = AVNav(cfg).eval()
    d, s, p = _batch(6, 3, cfg)
    starts = torch.zeros(6, 3)
    starts[0] = 1
    starts[3, 1] = 1  # batch element 1 starts a new episode at t = 3
    with torch.no_grad():
        mean, value, h = m(d, s, p, torch.randn(1, 3, cfg.hidden), starts)
        assert mean.shape == (6, 3, 2) and value.shape == (6, 3) and h.shape == (1, 3, cfg.hidden)
        assert mean.abs().max() <= 1 and torch.isfinite(value).all()
        fresh, _, _ = m(d[3:, 1:2], s[3:, 1:2], p[3:, 1:2], m.initial_state(1), torch.tensor([[1.0], [0.0], [0.0]]))
    assert torch.allclose(mean[3:, 1:2], fresh, atol=1e-6)  # what came before the start is forgotten


def test_behaviour_cloning_fits_the_expert_and_masks_padding():
    cfg = AVNavConfig()
    rng = np.random.default_rng(0)
    data = Dataset(cap=10_000)
    for n in (40, 25):  # two episodes: the second chunk of each is padded
        data.add({"d": list(rng.integers(0, 255, (n, 64, 64), np.uint8)),
                  "s": list(rng.integers(0, 255, (n, *cfg.spec_shape), np.uint8)),
                  "p": list(rng.standard_normal((n, 4)).astype(np.float32)),
                  "a": list(np.tile([0.6, -0.3], (n, 1)).astype(np.float32))})
    assert data.frames == 65
    batches = list(data.batches(rng, 32, 8))
    assert sum(float(b["m"].sum()) for b in batches) == 65  # every frame once, padding masked out
    torch.manual_seed(0)
    m = AVNav(cfg)
    opt = torch.optim.Adam(m.parameters(), lr=1e-3)
    first = last = None
    for _ in range(30):
        for b in batches:
            st = torch.zeros(b["m"].shape)
            st[0] = 1
            mean, _, _ = m(b["d"][..., None].float() / 25.5, b["s"].float() / 12.75, b["p"],
                           m.initial_state(b["m"].shape[1]), st)
            loss = (((mean - b["a"]) ** 2).sum(-1) * b["m"]).sum() / b["m"].sum()
            opt.zero_grad()
            loss.backward()
            opt.step()
            first = float(loss) if first is None else first
            last = float(loss)
    assert last < 0.05 * first


def test_a_short_dagger_run_checkpoints_logs_and_plays_through_the_harness(tmp_path):
    from app.tasks.evaluate import run_eval

    cfg = ImitationConfig(frames=160, iterations=2, val_episodes=1, epochs=1, seed=3)
    res = train(cfg, tmp_path / "run")
    ck = tmp_path / "run" / "model.pt"
    assert res["checkpoint"] == str(ck) and ck.is_file()
    rows = list(csv.DictReader(open(tmp_path / "run" / "log.csv")))
    assert [int(r["iteration"]) for r in rows] == [0, 1] and float(rows[0]["beta"]) == 1.0
    assert int(rows[-1]["frames"]) >= 160 and float(rows[-1]["loss"]) > 0
    from sonicverse_core.errors import ConfigError

    with pytest.raises(ConfigError, match="exists"):  # a finished run is never overwritten
        train(cfg, tmp_path / "run")
    model, meta = load(ck)
    assert meta["recipe"] == "dagger" and len(meta["log"]) == 2
    out = run_eval("AudioGoal", "av-nav", 1, split="val", checkpoint=str(ck), env_kwargs={"max_steps": 40})
    assert out["episodes"] == 1 and out["steps_per_episode"] <= 40


def test_own_policies_plug_in_and_bad_checkpoints_fail_clearly(tmp_path, cli):
    from agents import make_agent
    from sonicverse_core.errors import ConfigError

    assert type(make_agent("agents.scripted:RandomAgent", np.random.default_rng(0))).__name__ == "RandomAgent"
    with pytest.raises(ConfigError, match="cannot load agent"):
        make_agent("no_such_module:Policy")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(ConfigError, match="not a Sonicverse AV-Nav checkpoint"):
        load(bad)
    r = cli("eval", "--task", "AudioGoal", "--agent", "av-nav", "--checkpoint", str(bad), "--episodes", "1")
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1 and "checkpoint" in r.stderr
    r = cli("eval", "--task", "AudioGoal", "--agent", "agents.scripted:RandomAgent", "--episodes", "1",
            "--max-steps", "5", "--json", "--csv", str(tmp_path / "e.csv"))
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["episodes"] == 1
    m = AVNav(AVNavConfig(depth_hw=(48, 48)))
    save(m, tmp_path / "small.pt", {"recipe": "test"})
    m2, meta = load(tmp_path / "small.pt")
    assert m2.cfg.depth_hw == (48, 48) and meta == {"recipe": "test"}
    save(m, tmp_path / "half.pt", {}, half=True)  # shipped checkpoints: float16 weights, half the size
    m3, _ = load(tmp_path / "half.pt")
    assert (tmp_path / "half.pt").stat().st_size < 0.6 * (tmp_path / "small.pt").stat().st_size
    for a, b in zip(m.state_dict().values(), m3.state_dict().values()):
        assert b.dtype == a.dtype and torch.allclose(a, b, rtol=1e-3, atol=1e-4)


def test_the_shipped_checkpoint_loads_and_beats_random():
    """The shipped AV-Nav (agents/checkpoints) on the first 8 test episodes of seed 0: random reaches none of them
    (0 of 30 in the README's table); the learned policy reaches some."""
    from app.tasks.evaluate import run_eval
    from agents.learned import default_checkpoint

    model, meta = load(default_checkpoint("av-nav", "AudioGoal"))
    assert meta["recipe"] == "dagger" and sum(p.numel() for p in model.parameters()) < 5_000_000
    learned = run_eval("AudioGoal", "av-nav", 8, split="test", seed=0)
    rnd = run_eval("AudioGoal", "random", 8, split="test", seed=0)
    assert learned["sr"]["mean"] >= 1 / 8 > rnd["sr"]["mean"]
