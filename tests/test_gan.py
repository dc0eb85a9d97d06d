"""The gan baseline (agents/gan.py): its estimator's likelihood, trilateration from levels whose errors share a part,
the level-distance law it reads, and the agent turning once, then driving to its estimate on observations only."""
import math

import numpy as np
import pytest

from agents.gan import DRIVE_FIT, GanAgent, fit_drive, shared_error_loglik
from sonicverse_core.tasks import make_env

SENSORS = ("depth", "spectrogram", "audio", "pose", "bump")


def test_shared_error_loglik_is_the_multivariate_normal_density():
    from scipy.stats import multivariate_normal

    rng = np.random.default_rng(0)
    m, cells, s = 5, 7, 0.3
    w = rng.uniform(2.0, 20.0, m)
    res = [rng.normal(0, 0.5, cells) for _ in range(m)]
    cov = np.diag(1.0 / w) + s * s * np.ones((m, m))
    ref = multivariate_normal(np.zeros(m), cov).logpdf(np.array(res).T)
    ours = shared_error_loglik(res, w, s)
    assert np.allclose(ours - ours[0], ref - ref[0], atol=1e-9)  # the same up to a constant
    # a shift shared by every residual costs little; the same spread between them costs much more
    shift = shared_error_loglik([np.array([0.4])] * 4, [16.0] * 4, s)
    spread = shared_error_loglik([np.array([v]) for v in (0.4, -0.4, 0.4, -0.4)], [16.0] * 4, s)
    assert float(shift[0]) > float(spread[0]) + 2.0


@pytest.fixture(scope="module")
def env():
    e = make_env("SemanticAudioNav", split="val", sensors=SENSORS)
    yield e
    e.close()


def _agent(env, seed=0):
    obs, info = env.reset(seed=seed)
    ag = GanAgent(np.random.default_rng(0))
    ag.reset(env.unwrapped, obs, info)
    return ag, obs, info


def test_levels_heard_at_four_places_round_it_trilaterate_the_goal_despite_a_shared_error(env):
    """Levels made from the model itself for a goal at g, heard at four places round it, all too loud by the same
    amount (the shared error, 0.3 in ln(distance + NEAR): a loud recording): the most probable cell is g's, clearly
    above every cell 1.5 m or more away."""
    from agents.semnav import LEVEL_FIT
    from assets_manifest.soundbank import CATEGORIES

    ag, _, _ = _agent(env)
    cat = "sofa"
    ag.ears.score[:] = 0.0
    ag.ears.score[CATEGORIES.index(cat)] = 1.0
    ag.ears.heard = 10
    g = np.array([1.1, -0.7])
    off = LEVEL_FIT["offset"][cat]
    for q in ([-2.0, -1.5], [3.0, 0.5], [1.5, 2.6], [0.0, -3.8]):
        q = np.array(q)
        d = float(np.linalg.norm(q - g))
        db = (math.log(d + ag.NEAR) - 0.3 - off - DRIVE_FIT["shift"]) / DRIVE_FIT["slope"]  # all sound nearer
        ag.add_level(q, db, False)
    est = ag.estimate()
    assert np.linalg.norm(est - g) <= 0.3, est  # the grid's cell (0.2 m) and the path metric's octile steps
    lp = ag.log_posterior()
    i, j = np.floor(g / ag.POST_CELL).astype(int) + ag.n // 2
    far = np.hypot(ag._gx - g[0], ag._gy - g[1]) > 1.5
    assert lp[i, j] > lp[far].max() + 0.1  # above every cell 1.5 m or more away (by 0.19: four levels say little)


def test_louder_is_nearer_on_the_oracles_drives():
    """The law the driving levels are read with (DRIVE_FIT), re-fitted on four training episodes: the level falls
    with the path distance, about as the shipped fit says."""
    fit = fit_drive(4, seed=7)
    assert fit["windows"] >= 20
    assert -0.09 < fit["slope"] < -0.02 and abs(fit["slope"] - DRIVE_FIT["slope"]) < 0.02, fit


def test_gan_turns_once_then_drives_to_its_estimate(env):
    ag, obs, info = _agent(env, seed=3)
    spin = ag.spin_left
    for _ in range(spin):
        a = ag.act(obs, info)
        assert a[0] == -a[1] and a[1] > 0 and a[2] < 0  # on the spot, to the left, no stop
        obs, _, term, trunc, info = env.step(a)
    x, y, _, _ = obs["pose"]
    assert math.hypot(x, y) < 0.05 and ag.spins == 1 and len(ag.bearings) == 1 and len(ag.levels) == 1
    est = ag.estimate()
    assert est is not None and np.isfinite(ag.log_posterior()).any()
    assert ag.trace == [{"step": spin, "spin": 1, "at": ag.trace[0]["at"], "estimate": est.tolist()}]
    start = obs["pose"][:2].copy()
    for _ in range(40):
        a = ag.act(obs, info)
        if a[0] + a[1] > 0:  # driving forward: to the goal it plans for, within 0.3 m of its estimate
            assert np.linalg.norm(ag.goal - ag.estimate()) <= 0.3 + 1e-9
        obs, _, term, trunc, info = env.step(a)
        if term or trunc:
            break
    assert term or np.linalg.norm(obs["pose"][:2] - start) > 0.5  # it drove
    assert len(ag.levels) > 1  # and heard the level on the way


def test_gan_rejects_a_pose_that_is_not_finite(env):
    from sonicverse_core.errors import ConfigError

    ag, obs, info = _agent(env)
    obs = dict(obs, pose=np.array([np.nan, 0.0, 0.0, 1.0], np.float32))
    with pytest.raises(ConfigError, match="finite pose"):
        ag.act(obs, info)


def test_gan_says_which_sensors_it_lacks(env):
    from sonicverse_core.errors import ConfigError

    obs, info = env.reset(seed=0)
    ag = GanAgent(np.random.default_rng(0))
    with pytest.raises(ConfigError, match="'audio', 'spectrogram' sensors"):
        ag.reset(env.unwrapped, {k: v for k, v in obs.items() if k not in ("audio", "spectrogram")}, info)
