"""The learned agents on a CUDA device (``--device cuda``): the same losses and actions as on the CPU, a short
DAgger and PPO run that checkpoint files loading on the CPU, and the bench's device rows. Those are marked ``gpu``:
`make test` (CI, no GPU) leaves them out, `make test-gpu` runs them and fails where torch sees no CUDA device; they
passed on the GPU machine lent in session 22 (README). The errors for a device that is not there run everywhere."""
import json

import numpy as np
import pytest
import torch

CUDA = torch.cuda.is_available()


@pytest.fixture
def cuda():
    assert CUDA, "the gpu tests need a CUDA device: run them where torch sees one (`make test-gpu`)"


@pytest.fixture
def fp32():
    """CUDA in full fp32 for the test (no TF32 in convolutions or matrix products), restored after it."""
    old = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = old


def test_a_device_that_is_not_there_is_a_clear_error(cli, tmp_path):
    from agents.models import resolve_device
    from sonicverse_core.errors import ConfigError

    assert resolve_device("cpu").type == "cpu" and resolve_device(None).type == "cpu"
    assert resolve_device("auto").type == ("cuda" if CUDA else "cpu")
    with pytest.raises(ConfigError, match="device must be one of"):
        resolve_device("tpu")
    if not CUDA:
        with pytest.raises(ConfigError, match="no CUDA device"):
            resolve_device("cuda")
        r = cli("train", "--device", "cuda", "--frames", "100", "--out", str(tmp_path / "t"))
        assert r.returncode == 2 and "no CUDA device" in r.stderr and not (tmp_path / "t").exists()
        r = cli("bench", "train", "--devices", "cpu", "cuda", "--steps", "20")
        assert r.returncode == 2 and "no CUDA device" in r.stderr


def _batch(model, T=12, B=3, seed=0):
    from agents.models import primitives_for

    g = torch.Generator().manual_seed(seed)
    H, W = model.cfg.depth_hw
    b = {"d": torch.randint(0, 255, (T, B, H, W), generator=g, dtype=torch.uint8),
         "s": torch.randint(0, 255, (T, B, *model.cfg.spec_shape), generator=g, dtype=torch.uint8),
         "p": torch.randn(T, B, 4, generator=g), "g": torch.randn(T, B, 3, generator=g),
         "a": torch.tensor(primitives_for(3))[torch.randint(0, 17, (T, B), generator=g)], "m": torch.ones(T, B)}
    if getattr(model, "category", None) is not None:
        b["c"] = torch.randint(0, model.cfg.n_categories, (T, B), generator=g)
    if getattr(model.cfg, "occupancy", 0):
        V = model.cfg.occupancy
        b["o"] = torch.randint(0, 2, (T, B, V, V), generator=g, dtype=torch.uint8)
    return b


@pytest.mark.gpu
@pytest.mark.parametrize("agent", ["av-nav", "savi", "multitask"])
def test_the_models_give_the_same_loss_gradients_and_actions_on_cuda(cuda, fp32, agent):
    import copy

    from agents.imitation import ImitationConfig, _policy_step, bc_loss, build_policy

    torch.manual_seed(0)
    cpu = build_policy(ImitationConfig(agent=agent, memory=4, occupancy=16), (2, 64, 49), 3)
    if hasattr(cpu, "stage"):
        cpu.stage(2)
    gpu = copy.deepcopy(cpu).cuda()
    assert gpu.device.type == "cuda" and gpu.initial_state(2).device.type == "cuda"
    b = _batch(cpu)
    lc, pc = bc_loss(cpu, b, 0.5)
    lg, pg = bc_loss(gpu, b, 0.5)
    assert abs(float(lc) - float(lg)) <= 1e-4 * abs(float(lc)) + 1e-5
    lc.backward()
    lg.backward()
    for (name, a), bb in zip(cpu.named_parameters(), gpu.parameters()):
        if a.grad is not None:
            assert torch.allclose(a.grad, bb.grad.cpu(), rtol=1e-3, atol=1e-5), name
    rng = np.random.default_rng(0)
    obs = {"depth": rng.uniform(0, 6, (64, 64, 1)).astype(np.float32),
           "spectrogram": rng.uniform(0, 8, (2, 64, 49)).astype(np.float32),
           "pose": rng.normal(size=4).astype(np.float32)}
    hc, hg = cpu.initial_state(1), gpu.initial_state(1)
    for t in range(5):  # the greedy actions and the carried state agree step by step
        ac, hc = _policy_step(cpu.eval(), obs, hc, t == 0)
        ag, hg = _policy_step(gpu.eval(), obs, hg, t == 0)
        assert np.array_equal(ac, ag) and hg.device.type == "cuda"
        assert torch.allclose(hc, hg.cpu(), rtol=1e-3, atol=1e-4)


@pytest.mark.gpu
def test_dagger_and_ppo_train_on_cuda_and_their_checkpoints_load_on_the_cpu(cuda, tmp_path):
    from agents.imitation import ImitationConfig, train
    from agents.models import load_policy
    from agents.ppo import PPOConfig, train as train_ppo

    train(ImitationConfig(frames=120, iterations=2, val_episodes=1, epochs=1, seed=3, rollout_steps=40,
                          device="cuda"), tmp_path / "bc")
    model, meta = load_policy(tmp_path / "bc" / "model.pt")
    assert model.device.type == "cpu" and meta["config"]["device"] == "cuda"
    assert all(v.device.type == "cpu" for v in torch.load(tmp_path / "bc" / "model.pt", weights_only=False)
               ["state"].values())
    res = train_ppo(PPOConfig(frames=96, envs=2, steps=24, epochs=1, val_episodes=1, val_every=1, seed=4,
                              init=str(tmp_path / "bc" / "best.pt"), device="cuda"), tmp_path / "ppo")
    assert res["param_spread"] == 0.0 and len(res["log"]) == 2
    assert all(np.isfinite(r["policy_loss"]) and np.isfinite(r["value_loss"]) for r in res["log"])
    assert load_policy(tmp_path / "ppo" / "model.pt")[0].device.type == "cpu"


@pytest.mark.gpu
def test_bench_train_times_each_model_on_each_device(cuda, cli):
    r = cli("bench", "train", "--steps", "20", "--workers", "1", "--agents", "av-nav", "savi",
            "--devices", "cpu", "cuda", check_rc=0)
    b = json.loads(r.stdout)
    assert set(b["devices"]) == {"cpu", "cuda"} and set(b["update_speedup"]) == {"av-nav", "savi"}
    assert all(v["update_frames_per_s"] > 0 for d in b["devices"].values() for v in d.values())


@pytest.mark.gpu
def test_dd_ppo_processes_that_share_one_gpu_reduce_over_gloo(cuda, cli, tmp_path):
    """Two processes on a one-GPU node: NCCL would refuse them (two ranks on one device), so they reduce over gloo,
    on CUDA tensors, and keep identical weights."""
    r = cli("train", "--recipe", "ppo", "--frames", "256", "--envs", "1", "--val-episodes", "0", "--nproc", "2",
            "--device", "cuda", "--out", str(tmp_path / "dd"), "--json", check_rc=0)
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert res["processes"] == 2 and res["param_spread"] == 0.0
