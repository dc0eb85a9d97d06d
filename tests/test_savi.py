"""SAVi and the multi-task model (agents/savi.py): the scene memory stepped one step at a time equals one call over
the sequence and forgets what came before an episode's start; the goal descriptor keeps the goal where it was heard
while the robot moves in silence; the depth projection and the scene's true occupancy agree on where the walls are;
SAVi's second stage freezes the goal predictor; a short imitation run of each trains, checkpoints and plays through the
harness; PPO fine-tunes it."""
import math

import numpy as np
import pytest
import torch

from agents.models import load_policy, primitives_for
from agents.savi import SAVi, SAViConfig, project_depth, true_occupancy


def _inputs(T, B, cfg, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(T, B, *cfg.depth_hw, 1, generator=g) * 6, torch.rand(T, B, *cfg.spec_shape, generator=g) * 3,
            torch.randn(T, B, cfg.pose_dim, generator=g))


def test_the_scene_memory_stepped_equals_one_call_and_forgets_before_an_episode_start():
    cfg = SAViConfig(primitives=primitives_for(3), memory=6, occupancy=16)
    torch.manual_seed(0)
    m = SAVi(cfg).eval()
    T, B = 22, 3
    d, s, p = _inputs(T, B, cfg)
    starts = torch.zeros(T, B)
    starts[0] = 1
    starts[9, 1] = 1  # element 1 starts a new episode at t = 9
    with torch.no_grad():
        whole, value, h = m(d, s, p, m.initial_state(B), starts)
        hs, steps = m.initial_state(B), []
        for t in range(T):
            o, _, hs = m(d[t:t + 1], s[t:t + 1], p[t:t + 1], hs, starts[t:t + 1])
            steps.append(o)
        # element 1 from its start on, alone: what came before the start is forgotten
        fresh, _, _ = m(d[9:, 1:2], s[9:, 1:2], p[9:, 1:2], m.initial_state(1), starts[9:, 1:2])
    assert whole.shape == (T, B, len(cfg.primitives)) and value.shape == (T, B) and torch.isfinite(whole).all()
    assert torch.allclose(whole, torch.cat(steps), atol=1e-4)  # the kept tokens cover every layer's window
    assert torch.allclose(h, hs, atol=1e-4)
    assert torch.allclose(whole[9:, 1:2], fresh, atol=1e-4)
    # a memory of one step (stage 1): the output at t depends on step t alone (and the goal descriptor)
    m.stage(1)
    with torch.no_grad():
        a, _, _ = m(d, s, p, m.initial_state(B), starts)
        d2 = d.clone()
        d2[5] = 0.0  # another depth image at t = 5
        b, _, _ = m(d2, s, p, m.initial_state(B), starts)
    assert torch.allclose(a[6:], b[6:], atol=1e-5) and not torch.allclose(a[5], b[5])


def test_savi_with_a_map_input_reads_it_from_its_step_on_and_asks_for_it():
    """``SAViConfig.map_shape`` (``train --map``): the egocentric map is part of each step's token, so changing the map
    at step t changes the output from t on and nothing before; stepping one step at a time equals one call; a model
    with a map input refuses to act without one."""
    cfg = SAViConfig(primitives=primitives_for(3), memory=4, map_shape=(6, 32, 32), map_kind="route")
    torch.manual_seed(0)
    m = SAVi(cfg).eval()
    T, B = 7, 2
    d, s, p = _inputs(T, B, cfg)
    mp = torch.rand(T, B, 6, 32, 32, generator=torch.Generator().manual_seed(1))
    starts = torch.zeros(T, B)
    starts[0] = 1
    with torch.no_grad():
        a, _, _ = m(d, s, p, m.initial_state(B), starts, egomap=mp)
        mp2 = mp.clone()
        mp2[3] = 0.0
        b, _, _ = m(d, s, p, m.initial_state(B), starts, egomap=mp2)
        hs, steps = m.initial_state(B), []
        for t in range(T):
            o, _, hs = m(d[t:t + 1], s[t:t + 1], p[t:t + 1], hs, starts[t:t + 1], egomap=mp[t:t + 1])
            steps.append(o)
    assert torch.allclose(a[:3], b[:3], atol=1e-6) and not torch.allclose(a[3], b[3], atol=1e-3)
    assert torch.allclose(a, torch.cat(steps), atol=1e-4)
    with pytest.raises(ValueError, match="egocentric map"):
        m(d, s, p, m.initial_state(B), starts)


def test_the_goal_descriptor_keeps_the_heard_goal_while_the_robot_moves_in_silence():
    """Heard at the start: the goal 2 m straight ahead. Then silence while the robot drives 1 m forward and turns 90
    degrees left: the descriptor must put the goal 1 m away, on the robot's right (bearing -90 degrees)."""
    cfg = SAViConfig(memory=4, n_categories=3)
    m = SAVi(cfg).eval()
    with torch.no_grad():
        m.goal_audio.weight.zero_()
        m.goal_audio.bias.copy_(torch.tensor([1.0, 0.0, math.log1p(2.0)]))  # bearing 0, 2 m
        m.category.weight.zero_()
        m.category.bias.copy_(torch.tensor([0.0, 3.0, 0.0]))
    T = 3
    spec = torch.zeros(T, 1, *cfg.spec_shape)
    spec[0] = 1.0  # heard at t = 0 only
    pose = torch.tensor([[0.0, 0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 1.0], [1.0, 0.0, 1.0, 0.0]])[:, None]  # x, y, sin, cos
    a = torch.zeros(T, 1, cfg.hidden)
    starts = torch.tensor([[1.0], [0.0], [0.0]])
    z = torch.zeros(1, 2)
    desc, est, cat, have = m.descriptor(a, spec, pose, z, torch.zeros(1, 3), torch.zeros(1, 1), starts)
    assert torch.allclose(est, torch.tensor([[2.0, 0.0]]), atol=1e-5)  # the odometry frame
    bearing = [math.degrees(math.atan2(float(x[0, 1]), float(x[0, 0]))) for x in desc[:, :, :2]]
    dist = [math.expm1(float(x[0, 2])) for x in desc]
    assert bearing[0] == pytest.approx(0, abs=1e-3) and dist[0] == pytest.approx(2.0, abs=1e-4)
    assert bearing[1] == pytest.approx(0, abs=1e-3) and dist[1] == pytest.approx(1.0, abs=1e-4)
    assert bearing[2] == pytest.approx(-90, abs=1e-3) and dist[2] == pytest.approx(1.0, abs=1e-4)
    assert int(cat.argmax()) == 1 and float(have) == 1.0
    # nothing heard yet: an empty descriptor
    d0, *_ = m.descriptor(a, torch.zeros_like(spec), pose, z, torch.zeros(1, 3), torch.zeros(1, 1), starts)
    assert float(d0.abs().max()) == 0.0


def test_the_depth_projection_and_the_true_occupancy_agree_on_the_walls():
    """In a real home, facing a wall: the cells the depth image sees as obstacles are occupied in the scene's
    navigability grid, and the floor it sees in front is free."""
    from agents.maps import SENSORS
    from sonicverse_core.tasks import make_env

    env = make_env("AudioGoal", split="train", sensors=SENSORS, width=64, height=64)
    try:
        hits, total, free_ok, free_n = 0, 0, 0, 0
        for seed in range(8):
            obs, _ = env.reset(seed=seed)
            w = env.unwrapped.privileged()["world"]
            V = 32
            truth = true_occupancy(w, V)
            local = project_depth(torch.from_numpy(obs["depth"][None]), V, env.unwrapped.cfg.hfov,
                                  w.robot.camera_height)[0].numpy()
            obst, seen = local[0] > 0, local[1] > 0
            # compare with a 1-cell tolerance (the grid's cells are 5 cm, these 16 cm)
            from scipy.ndimage import binary_dilation

            near_truth = binary_dilation(truth > 0, iterations=1)
            hits += int((obst & near_truth).sum())
            total += int(obst.sum())
            floor = seen & ~obst
            free_ok += int((floor & (truth == 0)).sum())
            free_n += int(floor.sum())
        # measured: 1.0 and 0.86; with the window's columns mirrored 0.74 and 0.78
        assert total > 100 and hits / total > 0.95, (hits, total)
        assert free_n > 300 and free_ok / free_n > 0.82, (free_ok, free_n)
    finally:
        env.close()


def test_savi_stage_two_freezes_the_goal_predictor_and_trains_the_rest():
    cfg = SAViConfig(primitives=primitives_for(2), memory=4, n_categories=15)
    torch.manual_seed(1)
    m = SAVi(cfg)
    m.stage(2)
    opt = torch.optim.Adam(m.parameters(), lr=1e-2)
    before = {k: v.clone() for k, v in m.state_dict().items()}
    d, s, p = _inputs(5, 2, cfg)
    starts = torch.zeros(5, 2)
    starts[0] = 1
    out, v, _ = m(d, s, p, m.initial_state(2), starts)
    (out.square().mean() + v.square().mean()).backward()
    opt.step()
    after = m.state_dict()
    for k in before:
        changed = not torch.equal(before[k], after[k])
        frozen = k.split(".")[0] in ("goal_net", "goal_audio", "category")
        assert changed != frozen or k.startswith("goal_head"), k  # goal_head: no loss here
    assert m.window == 4


@pytest.mark.parametrize("agent", ["savi", "multitask"])
def test_a_short_imitation_run_trains_checkpoints_and_plays(tmp_path, agent):
    import csv

    from agents.imitation import ImitationConfig, train
    from app.tasks.evaluate import run_eval

    # SAVi reads sem-nav's route (train --agent savi --map route --teacher scripted), the multi-task model no map
    route = {"egomap": True, "route": True, "teacher": "scripted", "learner": "drawn"} if agent == "savi" else {}
    cfg = ImitationConfig(task="SemanticAudioNav", agent=agent, frames=120, iterations=3, val_episodes=0, epochs=1,
                          seed=2, rollout_steps=40, memory=4, occupancy=16, **route)
    train(cfg, tmp_path / "run")
    rows = list(csv.DictReader(open(tmp_path / "run" / "log.csv")))
    assert len(rows) == 3 and float(rows[-1]["category_loss"]) > 0
    assert ("occupancy_loss" in rows[0]) == (agent == "multitask")
    model, meta = load_policy(tmp_path / "run" / "model.pt")
    assert isinstance(model, SAVi) and model.arch == agent and meta["config"]["agent"] == agent
    assert (model.occ is not None) == (agent == "multitask")
    assert model.cfg.map_shape == ((6, 32, 32) if route else ()) and (model.egomap is not None) == bool(route)
    assert not route or model.cfg.map_kind == "route2"
    assert model.window == 4 and meta["window"] == 4  # the second stage's memory (iterations 1-2)
    from agents.models import save_policy

    save_policy(model, tmp_path / "first.pt", {**meta, "window": 1})  # a first-stage checkpoint acts as it trained
    assert load_policy(tmp_path / "first.pt")[0].window == 1
    out = run_eval("SemanticAudioNav", agent, 1, split="val", checkpoint=str(tmp_path / "run" / "model.pt"),
                   env_kwargs={"max_steps": 30})
    assert out["episodes"] == 1 and out["steps_per_episode"] <= 30
    from sonicverse_core.errors import ConfigError

    with pytest.raises(ConfigError, match="not a Sonicverse AV-Nav checkpoint"):
        load_policy(tmp_path / "run" / "model.pt", "av-nav")
    if agent == "savi":  # PPO fine-tunes it (its second stage)
        from agents.ppo import PPOConfig, train as train_ppo

        res = train_ppo(PPOConfig(task="SemanticAudioNav", frames=48, envs=2, steps=12, epochs=1, val_episodes=0,
                                  init=str(tmp_path / "run" / "model.pt"), seed=1), tmp_path / "ppo")
        tuned, meta = load_policy(tmp_path / "ppo" / "model.pt")
        assert isinstance(tuned, SAVi) and meta["recipe"] == "ppo" and res["param_spread"] == 0.0


def test_the_goal_predictor_pretrains_on_audible_frames_and_tells_categories_apart():
    """SAVi's goal predictor trained alone (agents.imitation.pretrain_goal): categories that sound different (here:
    which band of the spectrogram carries energy) are told apart on held-out episodes; silent frames are left out."""
    from agents.imitation import Dataset, pretrain_goal

    cfg = SAViConfig(n_categories=5, memory=4)
    rng = np.random.default_rng(0)
    data = Dataset(cap=100_000)
    for i in range(30):
        k = i % 5
        s = np.zeros((24, *cfg.spec_shape), np.uint8)
        s[:12, :, k * 12:(k + 1) * 12] = rng.integers(120, 255, (12, 2, 12, cfg.spec_shape[2]))  # then silence
        data.add({"s": list(s), "c": [np.int64(k)] * 24, "g": list(rng.standard_normal((24, 3)).astype(np.float32)),
                  "a": list(np.zeros((24, 2), np.float32))})
    torch.manual_seed(0)
    m = SAVi(cfg)
    out = pretrain_goal(m, data, np.random.default_rng(1), steps=120, batch=32)
    assert out["audible_frames"] == 30 * 12 and out["category_acc_test"] >= 0.9


@pytest.mark.parametrize("agent,first", [("savi", 6), ("multitask", 1)])
def test_the_shipped_checkpoints_load_and_beat_random(agent, first, audiogoal_random_test9):
    """The shipped SAVi and multi-task AudioGoal policies on a test episode of seed 0 where each is known to succeed
    (session 48: SAVi in episode 6 in 66 steps, not in 7 or 8, 22.5% of 200 in the README's table; the multi-task
    model in episode 1 in 90 steps, not in 2). Random reaches none of the first 9 here and none of the README's 200.
    One episode each: a failure plays all 500 steps, and the suite's budget is tight."""
    from agents.learned import default_checkpoint
    from app.tasks.evaluate import run_eval

    model, meta = load_policy(default_checkpoint(agent, "AudioGoal"))
    assert model.arch == agent and meta["recipe"] == "dagger" and sum(p.numel() for p in model.parameters()) < 6e6
    learned = run_eval("AudioGoal", agent, 1, split="test", seed=0, first=first)
    rnd = audiogoal_random_test9
    assert rnd["sr"]["n"] == 9 and rnd["sr"]["mean"] == 0
    assert learned["sr"]["mean"] == 1
