"""The envs work with the RL libraries people use: gym.make in a fresh interpreter as README says, SB3's check_env,
a few hundred PPO steps on a 2-env vectorised set-up for every registered env, info["is_success"], the spec's step
limit, and envs that close without touching each other's GL context."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sonicverse_core.tasks import ENV_IDS

ROOT = Path(__file__).resolve().parents[1]
SMALL = dict(homes=1, width=40, height=40)  # 40x40 camera (SB3's NatureCNN needs 36+): the contract, not vision


def test_gym_make_in_a_fresh_interpreter_as_the_readme_says():
    code = ("import gymnasium as gym\n"
            "env = gym.make('sonicverse_core.tasks:Sonicverse/AudioGoal-v0', homes=1, sensors=('audio', 'pose'))\n"
            "obs, info = env.reset(seed=0)\n"
            "obs, r, term, trunc, info = env.step(env.action_space.sample())\n"
            "print(env.spec.max_episode_steps, sorted(obs), 'is_success' in info)\n")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert p.returncode == 0, p.stderr[-2000:]
    assert p.stdout.split() == ["500", "['audio',", "'pose']", "True"]
    readme = (ROOT / "README.md").read_text()
    assert "gym.make(\"sonicverse_core.tasks:Sonicverse/AudioGoal-v0\"" in readme


@pytest.mark.parametrize("env_id", sorted(ENV_IDS.values()))
def test_sb3_check_env_and_ppo_on_two_vectorised_envs(env_id, tmp_path, monkeypatch):
    import gymnasium as gym
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_checker import check_env
    from stable_baselines3.common.env_util import make_vec_env

    from sonicverse_core.tasks.registry import task_spec

    env = gym.make(env_id, **SMALL)
    assert env.spec.max_episode_steps == task_spec(env_id).max_steps == env.unwrapped.cfg.max_steps
    check_env(env.unwrapped, warn=False, skip_render_check=True)
    env.close()
    vec = make_vec_env(env_id, n_envs=2, seed=0, env_kwargs=SMALL)
    monkeypatch.setenv("SB3_LOGDIR", str(tmp_path))  # SB3 makes its logger's folder even when silent: not in /tmp
    model = PPO("MultiInputPolicy", vec, n_steps=64, batch_size=64, n_epochs=1, seed=0, device="cpu", verbose=0)
    model.learn(total_timesteps=256)
    assert model.num_timesteps >= 256
    obs = vec.reset()
    act, _ = model.predict(obs, deterministic=True)
    assert act.shape == (2, vec.action_space.shape[0]) and np.all(np.isfinite(act))
    vec.close()


def test_closing_one_env_leaves_the_other_working():
    """Closing an env frees its own GL context only (before, pyrender terminated the process-wide EGL display)."""
    import gymnasium as gym

    a = gym.make("Sonicverse/AudioGoal-v0", **SMALL)
    b = gym.make("Sonicverse/AudioGoal-v0", **SMALL)
    a.reset(seed=0)
    b.reset(seed=1)
    a.close()
    for _ in range(3):
        obs, *_ = b.step(b.action_space.sample())
    assert obs["depth"].max() > 0  # still rendering
    c = gym.make("Sonicverse/AudioGoal-v0", **SMALL)  # and a new one starts
    obs, _ = c.reset(seed=2)
    assert obs["depth"].max() > 0
    b.close()
    c.close()


def test_an_env_dropped_without_closing_leaves_the_others_working():
    """The garbage collector taking an env nobody closed (a notebook's habit) frees its GL context only: pyrender's
    own clean-up terminated the process-wide EGL display, and every other env's camera failed on its next frame."""
    import gc

    import gymnasium as gym

    a = gym.make("Sonicverse/AudioGoal-v0", **SMALL)
    b = gym.make("Sonicverse/AudioGoal-v0", **SMALL)
    a.reset(seed=0)
    b.reset(seed=1)
    del a
    gc.collect()
    for _ in range(3):
        obs, *_ = b.step(b.action_space.sample())
    assert obs["depth"].max() > 0
    b.close()


def test_info_reports_is_success_for_the_ecosystem():
    import gymnasium as gym

    env = gym.make("Sonicverse/AudioPointGoal-v0", sensors=("audio", "pose", "pointgoal"), homes=1)
    obs, info = env.reset(seed=3)
    assert info["is_success"] is False
    _, _, _, _, info = env.step(np.zeros(2, np.float32))
    assert info["is_success"] == info["success"]
    env.close()
