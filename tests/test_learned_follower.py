"""Learned agents that read a map (agents/following.py's EgoMap, `train --map`): the learned speaker follower headless
and in the VR loop, the map it reads, training and playing such a policy and where it is refused, the floor shield it
acts through, and ensembles of policies (`train --ensemble`)."""
import json

import numpy as np
import pytest
import torch

from agents.imitation import ImitationConfig, train
from agents.models import AVNav, AVNavConfig, load, load_policy, save


def test_the_floor_shield_removes_the_actions_that_would_leave_the_floor_and_only_those():
    """`agents.following.floor_safe` on a 6 x 4 m room (navigable to 0.205 m of its walls, the robot's radius and
    half a cell): 0.1 m short of that edge, facing it, the forward actions whose 0.3 s reach crosses it are removed
    and the slow ones and the turns on the spot stay; facing away, every action stays. `_policy_step` draws only
    allowed actions, and with none allowed acts as if unshielded."""
    from agents.following import floor_safe
    from agents.imitation import _policy_step
    from agents.models import primitives_for
    from sonicverse_core.geometry.navgrid import NavGrid
    from sonicverse_core.scene import load_scene
    from sonicverse_core.world import RobotConfig

    grid, robot = NavGrid(load_scene("shoebox:6x4x3")), RobotConfig()
    table = np.array(primitives_for(2))
    edge = 6.0 - 0.205
    ok = floor_safe(table, grid, (edge - 0.1, 2.0, 0.0), robot, 0.3)
    reach = 0.5 * (table[:, 0] + table[:, 1]) * robot.max_speed * 0.3  # straight-line reach; veers reach less far
    assert not ok[0] and not ok[1]  # full speed (0.21 m) and half (0.105 m) would cross the edge
    assert ok[2] and all(ok[reach <= 0])  # a quarter (0.05 m), the turns on the spot, standing still stay
    assert ok[reach < 0.09].all() and not ok[reach > 0.11].any()
    assert floor_safe(table, grid, (edge - 0.1, 2.0, 180.0), robot, 0.3).all()
    assert not floor_safe(table, grid, (edge - 0.1, 2.0, 0.0), robot, 1.0)[2]  # a quarter for 1 s: 0.175 m

    cfg = AVNavConfig(primitives=primitives_for(2))
    m = AVNav(cfg).eval()
    with torch.no_grad():
        m.actor.weight.zero_()
        m.actor.bias.fill_(0.0)
        m.actor.bias[0] = 5.0  # full speed ahead: by far the most likely
    obs = {"depth": np.full((64, 64, 1), 2.0, np.float32), "spectrogram": np.ones(cfg.spec_shape, np.float32),
           "pose": np.zeros(4, np.float32)}
    rng = np.random.default_rng(0)
    drawn = {tuple(_policy_step(m, obs, m.initial_state(1), True, rng, allowed=ok)[0]) for _ in range(100)}
    assert drawn <= {tuple(a) for a in table[ok]} and len(drawn) > 3
    assert tuple(_policy_step(m, obs, m.initial_state(1), True, None, allowed=ok)[0]) in {tuple(a) for a in table[ok]}
    none = np.zeros(len(table), bool)
    assert tuple(_policy_step(m, obs, m.initial_state(1), True, None, allowed=none)[0]) == tuple(table[0])



def test_the_fine_head_holds_the_coarse_actions_and_halves_the_veering_step():
    """``--head fine``: 25 wheel pairs holding the 16 of the default head, the veers every 0.125 instead of 0.25, so
    any veer the scripted follower commands (inner wheel anywhere in [0, 1] of the outer) lies within 0.0625 of one;
    a policy built with it has 25 outputs and its labels are the nearest of them."""
    from agents.imitation import ImitationConfig, build_policy
    from agents.models import primitives_for

    coarse, fine = np.array(primitives_for(2)), np.array(primitives_for(2, fine=True))
    assert len(fine) == 25 == len({tuple(p) for p in fine})
    assert {tuple(p) for p in coarse} <= {tuple(p) for p in fine}
    veers = np.stack([np.linspace(0.0, 1.0, 401), np.ones(401)], 1)
    gap = lambda table: np.sqrt(((veers[:, None] - table[None]) ** 2).sum(-1)).min(1).max()  # noqa: E731
    assert gap(fine) == pytest.approx(0.0625) and gap(coarse) == pytest.approx(0.125)
    m = build_policy(ImitationConfig(task="SpeakerFollowing", head="fine", egomap=True), AVNavConfig().spec_shape, 2)
    assert m.actor.out_features == 25 and np.allclose(m.table.numpy(), fine)
    a = torch.tensor([[0.94, 1.0], [1.0, 0.3]])
    assert fine[m.label(a).numpy()].tolist() == [[1.0, 1.0], [1.0, 0.25]]  # 0.94: 1.0 is nearer than 0.875

def test_the_learned_speaker_follower_runs_headless_and_in_the_vr_loop(cli, tmp_path, monkeypatch):
    """`task run speaker-following --agent av-nav` builds the env with the sensors the checkpoint was trained on;
    in the VR loop the robot's agent gets the same observations (depth at its size, the spectrogram of its ears)."""
    from agents.learned import default_checkpoint
    from app.tasks.in_the_loop import FollowMe
    from app.vr.headless import HeadlessBackend
    from app.vr.session import SessionConfig, VRSession
    from sonicverse_core.errors import ConfigError

    model, meta = load_policy(default_checkpoint("av-nav", "SpeakerFollowing"))  # an ensemble since session 36
    assert meta["config"]["task"] == "SpeakerFollowing" and model.cfg.action_dim == 2
    r = cli("task", "run", "speaker-following", "--agent", "av-nav", "--episodes", "1", "--max-steps", "30",
            "--json", "--out", str(tmp_path), check_rc=0)
    res = json.loads(r.stdout)
    assert res["agent"] == "av-nav" and res["time_in_band"]["n"] == 1 and res["time_s"]["mean"] <= 3.0 + 1e-9
    # the shipped follower keeps the band more than random on test episode 1 (session 33, the map policy on the
    # scripted follower's actions: 1.0 against 0.05; the first 8, 0.76 against 0.09; the README's 30 episodes:
    # 0.734 against 0.088)
    from app.tasks.run import run_task

    res = run_task("speaker-following", "av-nav", 1, seed=0, first=1)
    learned = res["time_in_band"]["mean"]
    rnd = run_task("speaker-following", "random", 1, seed=0, first=1)["time_in_band"]["mean"]
    assert learned > rnd + 0.1, (learned, rnd)
    # the floor shield (AVNavAgent.shield_s): on this episode the policy bumps 6 times without it and once with it
    # (session 36's file: 5 and 0)
    assert res["collisions"]["mean"] <= 1
    monkeypatch.setattr("agents.learned.AVNavAgent.shield_s", None)
    assert run_task("speaker-following", "av-nav", 1, seed=0, first=1)["collisions"]["mean"] >= \
        res["collisions"]["mean"] + 3
    monkeypatch.undo()
    with pytest.raises(ConfigError, match="--checkpoint is for learned agents"):
        run_task("speaker-following", "oracle", 1, checkpoint=default_checkpoint("av-nav", "SpeakerFollowing"))
    task = FollowMe(agent="av-nav", seed=0)
    seen = []
    cfg = SessionConfig(scene="builtin:apartment?seed=6000", views=True, audio="offline", robots=1, write_frames=0)
    with VRSession(cfg, HeadlessBackend(target_hz=30.0, width=64, height=64), task=task) as s:
        act = task.agent.act
        task.agent.act = lambda obs, info: (seen.append({k: v.shape for k, v in obs.items()}), act(obs, info))[1]
        s.run(frames=30 * 3)
    assert task.steps >= 25 and seen
    assert seen[-1]["spectrogram"] == model.cfg.spec_shape and seen[-1]["depth"] == (*model.cfg.depth_hw, 1)
    with pytest.raises(ConfigError, match="unknown agent 'savi'"):
        FollowMe(agent="savi")


def test_the_egocentric_map_draws_the_floor_and_the_person_where_they_are():
    """EgoMap (`train --map`): the robot at the centre facing the top, its left to the left; the floor under the
    robot is navigable; a person the camera sees is drawn within a pixel or two of where they stand (the median),
    and so is the belief's likeliest place in view; the scripted follower's route starts at the robot."""
    from agents.following import EgoMap, OracleFollower
    from agents.maps import MAP_SENSORS
    from sonicverse_core.tasks import make_env

    env = make_env("SpeakerFollowing", split="val", sensors=MAP_SENSORS, width=64, height=64)
    try:
        obs, info = env.reset(seed=3)
        ego, oracle = EgoMap(np.random.default_rng(0)), OracleFollower(np.random.default_rng(0))
        ego.reset(env, obs, info)
        oracle.reset(env, obs, info)
        S, c, errs, routed = EgoMap.SIZE, EgoMap.SIZE // 2, [], 0
        for _ in range(160):
            img = ego.observe(obs, info)
            assert img.shape == (EgoMap.CHANNELS, S, S) and img.dtype == np.uint8
            assert img[0, c - 1:c + 1, c - 1:c + 1].max() == 255  # the robot stands on the floor
            priv = env.unwrapped.privileged()
            w, person = priv["world"], priv["person"]
            d, a = person.pos[:2] - w.pose[:2], np.radians(w.pose[2])
            fwd, left = np.cos(a) * d[0] + np.sin(a) * d[1], -np.sin(a) * d[0] + np.cos(a) * d[1]
            truth = np.array([c - fwd / EgoMap.RES, c - left / EgoMap.RES])
            if ego.mode == "seen" and max(abs(fwd), abs(left)) < 3.5:
                seen = np.argwhere(img[2] == img[2].max()).mean(0) + 0.5
                best = np.argwhere(img[1] == img[1].max()).mean(0) + 0.5
                errs.append((np.hypot(*(seen - truth)), np.hypot(*(best - truth))))
            if img[3].any():
                near = np.argwhere(img[3] > 0)
                assert np.abs(near - (c - 0.5)).max(1).min() <= 2.0  # the route starts at the robot
                routed += 1
            obs, _, term, trunc, info = env.step(oracle.act(obs, info))
            if term or trunc:
                break
        assert len(errs) >= 50 and routed >= 1, (len(errs), routed)
        e = np.array(errs)  # pixels of 0.25 m: the camera's person detector is not exact, nor is the belief
        assert np.median(e[:, 0]) <= 1.5 and np.median(e[:, 1]) <= 2.0, np.median(e, 0)
        assert np.percentile(e, 90, axis=0).max() <= 4.0, np.percentile(e, 90, axis=0)
    finally:
        env.close()


def test_a_policy_with_a_map_trains_plays_and_is_refused_where_it_does_not_belong(tmp_path, cli, policy_batch):
    """`train --map`: av-nav on SpeakerFollowing reads the egocentric map besides depth, spectrogram and pose; it
    trains (here on the scripted follower's actions, `--teacher scripted`), its checkpoint records the map's shape
    and kind, and the harness plays it with the sensors it needs (the raw audio block for the belief). On AudioGoal
    it reads the map the robot draws (NavEgoMap), on SemanticAudioNav that and the semantic camera's sightings of
    the category its ears name (SemNavMap, with the semantic sensor; there `--teacher scripted` is sem-nav).
    Elsewhere `--map` (and `--map route` off the navigation tasks), and `--teacher scripted` without those maps, are
    one line and exit 2. PPO fine-tunes such a policy with its map and floor shield."""
    from agents.following import EgoMap
    from agents.maps import SENSORS, ego_for, floor_shield, sensors_for
    from agents.navmap import NavEgoMap, SemNavMap
    from agents.ppo import PPOConfig, train as train_ppo
    from app.tasks.run import run_task

    cfg = ImitationConfig(task="SpeakerFollowing", frames=80, iterations=1, val_episodes=0, epochs=1, seed=3,
                          rollout_steps=40, egomap=True, teacher="scripted", learner="drawn")
    train(cfg, tmp_path / "m")
    model, meta = load(tmp_path / "m" / "model.pt")
    assert model.cfg.map_shape == (EgoMap.CHANNELS, EgoMap.SIZE, EgoMap.SIZE) and meta["config"]["egomap"]
    assert model.cfg.map_kind == "follow" and meta["config"]["teacher"] == "scripted"
    # navigation: the map the robot draws; the learner drawing its actions in collection (`--learner drawn`) meets
    # no floor shield there (no floor plan), on the follower's map it does
    train(ImitationConfig(task="AudioGoal", frames=40, iterations=1, val_episodes=0, epochs=1, seed=3,
                          rollout_steps=40, egomap=True, learner="drawn", beta0=0.0, beta_min=0.0), tmp_path / "n")
    nav, nmeta = load(tmp_path / "n" / "model.pt")
    assert nav.cfg.map_kind == "nav" and nav.cfg.map_shape == (NavEgoMap.CHANNELS, NavEgoMap.SIZE, NavEgoMap.SIZE)
    assert type(ego_for(nav)) is NavEgoMap and sensors_for(nav) == SENSORS  # no raw audio block needed
    assert nmeta["config"]["learner"] == "drawn" and floor_shield(nav, ego_for(nav)) is None
    res = run_task("audio-goal", "av-nav", 1, seed=0, checkpoint=str(tmp_path / "n" / "model.pt"),
                   env_kwargs={"max_steps": 20})  # the av-nav agent plays a navigator with a map, unshielded
    assert res["episodes"] == 1
    # SemanticAudioNav: that map and where the semantic camera saw the category the ears name (SemNavMap), on
    # sem-nav's actions (`--teacher scripted`: the map's sem-nav acts, its action the label)
    train(ImitationConfig(task="SemanticAudioNav", frames=30, iterations=1, val_episodes=0, epochs=1, seed=3,
                          rollout_steps=30, egomap=True, teacher="scripted"), tmp_path / "s")
    sem, smeta = load(tmp_path / "s" / "model.pt")
    assert sem.cfg.map_kind == "sem" and sem.cfg.map_shape == (SemNavMap.CHANNELS, SemNavMap.SIZE, SemNavMap.SIZE)
    assert type(ego_for(sem)) is SemNavMap and sensors_for(sem) == SENSORS + ("semantic", "audio")
    assert smeta["config"]["teacher"] == "scripted" and not ego_for(sem).teach  # it plays without a teacher
    res = run_task("semantic-audio-nav", "av-nav", 1, seed=0, checkpoint=str(tmp_path / "s" / "model.pt"),
                   env_kwargs={"max_steps": 20})
    assert res["episodes"] == 1
    with pytest.raises(ValueError, match="egomap"):  # a map policy never acts without its map
        model(*policy_batch(1, 1, model.cfg), model.initial_state(1), torch.ones(1, 1))
    res = run_task("speaker-following", "av-nav", 1, seed=0, checkpoint=str(tmp_path / "m" / "model.pt"),
                   env_kwargs={"max_steps": 30})
    assert res["episodes"] == 1 and res["time_s"]["mean"] <= 3.0 + 1e-9
    r = cli("train", "--agent", "sound-localizer", "--task", "AudioGoal", "--map", "--frames", "100", "--out",
            str(tmp_path / "x"), check_rc=2)  # the navigators read maps (av-nav, savi, multitask), not the localiser
    assert "--map is for" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = cli("train", "--task", "AudioGoal", "--map", "--teacher", "scripted", "--frames", "100", "--out",
            str(tmp_path / "y"), check_rc=2)
    assert "--teacher scripted is for" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = cli("train", "--task", "SpeakerFollowing", "--map", "route", "--frames", "100", "--out", str(tmp_path / "w"),
            check_rc=2)  # sem-nav's route is for the navigation tasks
    assert "--map route" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = cli("train", "--recipe", "ppo", "--learner", "drawn", "--frames", "100", "--out", str(tmp_path / "z"),
            check_rc=2)
    assert "--learner is for" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    # PPO fine-tunes a map policy as it plays: its map drawn per env and the floor shield's mask, replayed in the
    # update (before the first step every probability ratio is 1: a map or mask not replayed would move it)
    kept = []  # model.pt is on disk after every val_every updates, without validation too (an interruption keeps it)
    res = train_ppo(PPOConfig(task="SpeakerFollowing", frames=32, envs=1, steps=16, val_episodes=0, critic_warmup=1,
                              val_every=1, init=str(tmp_path / "m" / "model.pt")), tmp_path / "p",
                    progress=lambda row: kept.append((tmp_path / "p" / "model.pt").exists()))
    assert len(res["log"]) == 2 and all(r["replay_err"] < 1e-4 for r in res["log"]), res["log"]
    assert kept == [True, True]
    tuned, tmeta = load(tmp_path / "p" / "model.pt")
    assert tuned.cfg.map_shape == model.cfg.map_shape and tmeta["recipe"] == "ppo"
    r = cli("train", "--val-every", "5", "--frames", "100", "--out", str(tmp_path / "w"), check_rc=2)
    assert "--val-every, --critic-warmup and --lr belong to --recipe ppo" in r.stderr


def test_an_ensemble_acts_on_the_mean_of_its_members_distributions(tmp_path, cli, policy_batch, capsys):
    """`train --ensemble A.pt B.pt`: one float16 file; where av-nav is expected it loads as a PolicyEnsemble whose
    action distribution is the mean of its members' (each with its own GRU state, stepping as it would alone), and
    the harness plays it; `train --unpack` gives each member back as its own checkpoint. Members of another
    configuration or task, a single member, an existing file: one line, exit 2."""
    from agents.imitation import _policy_step
    from agents.models import PolicyEnsemble, load_policy, primitives_for
    from app.tasks.run import run_task

    cfg = AVNavConfig(primitives=primitives_for(2))
    paths = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        paths.append(tmp_path / f"m{seed}.pt")
        save(AVNav(cfg).eval(), paths[-1], {"config": {"task": "AudioGoal", "seed": seed}, "iteration": 3})
    r = cli("train", "--task", "AudioGoal", "--ensemble", *map(str, paths), "--out", str(tmp_path / "e"), "--json")
    res = json.loads(r.stdout)
    ens, meta = load_policy(res["checkpoint"], "av-nav")
    assert isinstance(ens, PolicyEnsemble) and [m["seed"] for m in meta["members"]] == [0, 1]
    assert meta["config"]["task"] == "AudioGoal" and res["bytes"] < 0.6 * sum(p.stat().st_size for p in paths)
    d, s, p = policy_batch(4, 2, cfg)
    starts = torch.zeros(4, 2)
    starts[0] = 1
    alone = [load(q)[0] for q in paths]
    with torch.no_grad():
        out, _, h = ens(d, s, p, ens.initial_state(2), starts)
        outs = [m(d, s, p, m.initial_state(2), starts) for m in ens.members]
        full = [m(d, s, p, m.initial_state(2), starts)[0] for m in alone]
    mean = torch.stack([torch.softmax(o[0], -1) for o in outs]).mean(0)
    assert torch.allclose(torch.softmax(out, -1), mean, atol=1e-6)
    assert h.shape == (2, 1, 2, cfg.hidden) and all(torch.equal(h[i], outs[i][2]) for i in range(2))
    # float16 weights: the distribution within 0.01 of the float32 members' mean
    assert (torch.softmax(out, -1) - torch.stack([torch.softmax(o, -1) for o in full]).mean(0)).abs().max() < 0.01
    obs = {"depth": np.full((64, 64, 1), 2.0, np.float32), "spectrogram": np.ones(cfg.spec_shape, np.float32),
           "pose": np.zeros(4, np.float32)}
    a, h1 = _policy_step(ens, obs, ens.initial_state(1), True, np.random.default_rng(0))
    assert any(np.allclose(a, t) for t in cfg.primitives) and h1.shape == (2, 1, 1, cfg.hidden)
    res_run = run_task("audio-goal", "av-nav", 1, seed=0, checkpoint=res["checkpoint"], env_kwargs={"max_steps": 8})
    assert res_run["episodes"] == 1
    # a policy without a map input joins whatever map kind its file names (files from before the field hold
    # "follow", later AudioGoal ones "nav"): the map it does not read is no difference
    nav = tmp_path / "nav.pt"
    save(AVNav(AVNavConfig(primitives=primitives_for(2), map_kind="nav")), nav, {"config": {"task": "AudioGoal"}})
    r = cli("train", "--task", "AudioGoal", "--ensemble", str(paths[0]), str(nav), "--out", str(tmp_path / "n"),
            "--json")
    assert isinstance(load_policy(json.loads(r.stdout)["checkpoint"], "av-nav")[0], PolicyEnsemble)
    other = tmp_path / "other.pt"
    save(AVNav(AVNavConfig(primitives=primitives_for(3))), other, {"config": {"task": "AudioGoal"}})
    sf = tmp_path / "sf.pt"
    save(AVNav(cfg), sf, {"config": {"task": "SpeakerFollowing"}})
    from app.cli import main  # the refusals in this process (the command's own entry point ran above)

    def refused(*argv) -> str:
        assert main(list(argv)) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and err.startswith("sonicverse: error:"), err
        return err

    for args, msg in (((paths[0], other), "share one configuration"), ((paths[0],), "two policies or more"),
                      ((paths[0], res["checkpoint"]), "an ensemble already"),
                      ((paths[0], sf), "trained on one task"), ((paths[0], paths[1]), "exists")):
        out_dir = tmp_path / ("e" if msg == "exists" else msg.replace(" ", "_"))
        assert msg in refused("train", "--task", "AudioGoal", "--ensemble", *map(str, args), "--out", str(out_dir))
    err = refused("train", "--task", "SpeakerFollowing", "--ensemble", *map(str, paths), "--out", str(tmp_path / "t"))
    assert "not SpeakerFollowing" in err and not (tmp_path / "t" / "best.pt").exists()
    for extra in (["--map"], ["--learner", "drawn"], ["--resume"]):  # training flags: refused, not ignored
        err = refused("train", "--task", "AudioGoal", "--ensemble", *map(str, paths), *extra, "--out",
                      str(tmp_path / "u"))
        assert "as they are" in err and not (tmp_path / "u" / "best.pt").exists()
    from agents.ppo import PPOConfig, train as train_ppo
    from sonicverse_core.errors import ConfigError

    with pytest.raises(ConfigError, match="ensemble"):
        train_ppo(PPOConfig(task="AudioGoal", frames=16, envs=1, init=res["checkpoint"]), tmp_path / "p")
    # `train --unpack`: each member back as its own checkpoint (the weights the ensemble stores, its own meta)
    assert main(["train", "--unpack", res["checkpoint"], "--out", str(tmp_path / "k")]) == 0
    for k, src in enumerate(paths):
        mine, mmeta = load(tmp_path / "k" / f"member{k}.pt")
        assert mmeta["config"]["seed"] == k
        assert all(torch.equal(v, ens.members[k].state_dict()[n]) for n, v in mine.state_dict().items())
    capsys.readouterr()
    assert "exists" in refused("train", "--unpack", res["checkpoint"], "--out", str(tmp_path / "k"))
    assert "not a Sonicverse policy ensemble" in refused("train", "--unpack", str(paths[0]), "--out",
                                                         str(tmp_path / "j"))
    assert "no training flags" in refused("train", "--unpack", res["checkpoint"], "--map", "--out",
                                          str(tmp_path / "i"))


def test_an_ensembles_temperature_sharpens_its_draw_and_lives_in_its_checkpoint(tmp_path, capsys):
    """`train --ensemble ... --temperature T` stores T in the file's meta; the player (``av-nav``) reads it and
    draws action k with probability p_k^(1/T) / sum_j p_j^(1/T): counted over 8,000 draws of a made-up
    distribution (within 0.015: over 4 standard errors). T = 1 draws as before; --temperature without
    --ensemble, or outside 0.05-10, is refused in one line."""
    from agents import make_agent
    from agents.imitation import _policy_step
    from agents.models import primitives_for
    from app.cli import main

    cfg = AVNavConfig(primitives=primitives_for(2))
    paths = []
    for seed in (0, 1):
        torch.manual_seed(seed)
        paths.append(tmp_path / f"m{seed}.pt")
        save(AVNav(cfg).eval(), paths[-1], {"config": {"task": "SpeakerFollowing", "seed": seed}})
    assert main(["train", "--task", "SpeakerFollowing", "--ensemble", *map(str, paths), "--temperature", "0.5",
                 "--out", str(tmp_path / "e"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["temperature"] == 0.5
    agent = make_agent("av-nav", np.random.default_rng(0), task="SpeakerFollowing",
                       checkpoint=tmp_path / "e" / "best.pt")
    assert agent.temperature == 0.5
    # the draw itself, on a model whose distribution is made up
    n = len(cfg.primitives)
    p = np.linspace(1.0, 3.0, n) ** 2
    p /= p.sum()

    class Fixed(torch.nn.Module):
        discrete, device = True, torch.device("cpu")
        table = torch.tensor(np.c_[np.arange(n), np.zeros(n)], dtype=torch.float32)  # action k: (k, 0)

        def forward(self, *a, **k):
            return torch.log(torch.tensor(p))[None, None], None, None

    obs = {"depth": np.zeros((64, 64, 1), np.float32), "spectrogram": np.zeros(cfg.spec_shape, np.float32),
           "pose": np.zeros(4, np.float32)}
    rng = np.random.default_rng(1)
    for T in (1.0, 0.5):
        counts = np.zeros(n)
        for _ in range(8_000):
            a, _ = _policy_step(Fixed(), obs, None, False, rng, temperature=T)
            counts[int(a[0])] += 1
        want = p ** (1 / T) / np.sum(p ** (1 / T))
        assert np.abs(counts / counts.sum() - want).max() < 0.015, (T, counts / counts.sum(), want)

    def refused(*argv) -> str:
        assert main(list(argv)) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and err.startswith("sonicverse: error:"), err
        return err

    assert "give it with --ensemble" in refused("train", "--task", "SpeakerFollowing", "--temperature", "0.5",
                                                 "--out", str(tmp_path / "x"))
    refused("train", "--task", "SpeakerFollowing", "--ensemble", *map(str, paths), "--temperature", "0",
            "--out", str(tmp_path / "y"))
