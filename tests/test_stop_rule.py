"""How a learned policy stops and what it may draw (agents.imitation._policy_step, agents.maps, agents.ppo): a stop
only where most likely, or where its probability reaches ``stop_at`` (the route av-nav's rule), the route map's stop
gate, and PPO drawing through the floor shield's mask."""
import numpy as np
import torch

from agents.models import AVNav, AVNavConfig


def _policy_with_a_stop(stop_bias: float, ahead_bias: float = 0.0):
    """An AV-Nav policy with the stop action whose logits are its actor's biases alone: ``stop_bias`` for the stop,
    ``ahead_bias`` for straight ahead, 0 for the rest; (config, model, the stop's index, an observation)."""
    from agents.models import primitives_for

    cfg = AVNavConfig(primitives=primitives_for(3))
    m = AVNav(cfg).eval()
    stop = [i for i, a in enumerate(cfg.primitives) if a[2] > 0][0]
    obs = {"depth": np.full((64, 64, 1), 2.0, np.float32), "spectrogram": np.ones(cfg.spec_shape, np.float32),
           "pose": np.zeros(4, np.float32)}
    with torch.no_grad():
        m.actor.weight.zero_()
        m.actor.bias.fill_(0.0)
        m.actor.bias[stop] = stop_bias
        m.actor.bias[0] = ahead_bias
    return cfg, m, stop, obs


def test_drawn_actions_stop_only_when_the_stop_is_the_most_likely_action():
    from agents.imitation import _policy_step

    _, m, _, obs = _policy_with_a_stop(2.0)  # stop: the most likely action
    a, _ = _policy_step(m, obs, m.initial_state(1), True, np.random.default_rng(0))
    assert a[2] > 0
    _, m, _, obs = _policy_with_a_stop(1.5, 2.0)  # straight ahead most likely; the stop still has a sixth of the mass
    rng = np.random.default_rng(1)
    drawn = [_policy_step(m, obs, m.initial_state(1), True, rng)[0] for _ in range(200)]
    assert all(a[2] < 0 for a in drawn) and len({tuple(a) for a in drawn}) > 3  # drawn, never the stop


def test_a_policy_stops_where_its_stops_probability_reaches_stop_at():
    """With ``stop_at`` (``AVNavAgent.stop_at``: 0.1 for the route av-nav) a drawn policy stops where the stop's
    probability reaches it, though another action is more likely; just below it, it never stops. Greedy acting (no
    Generator) keeps the most likely action."""
    from agents.imitation import _policy_step
    from agents.learned import AVNavAgent, MultitaskAgent, SAViAgent
    from agents.maps import STOP_AT

    # the shipped route policies' figures were measured with it (av-nav since session 68, the others since 69)
    assert AVNavAgent.stop_at == SAViAgent.stop_at == MultitaskAgent.stop_at == STOP_AT == 0.1
    cfg, m, stop, obs = _policy_with_a_stop(1.5, 2.0)  # straight ahead the most likely
    p_stop = float(torch.softmax(m.actor.bias.detach().double(), 0)[stop])
    assert 0.1 < p_stop < 0.3
    rng = np.random.default_rng(2)
    at = [_policy_step(m, obs, m.initial_state(1), True, rng, stop_at=p_stop * 0.99)[0] for _ in range(20)]
    assert all(a[2] > 0 for a in at)
    below = [_policy_step(m, obs, m.initial_state(1), True, rng, stop_at=p_stop * 1.01)[0] for _ in range(200)]
    assert all(a[2] < 0 for a in below) and len({tuple(a) for a in below}) > 3
    greedy, _ = _policy_step(m, obs, m.initial_state(1), True, None, stop_at=p_stop * 0.5)
    assert tuple(greedy) == tuple(cfg.primitives[0])


def test_a_route_policy_may_stop_only_while_its_maps_sem_nav_faces_its_target():
    """``agents.maps.stop_gate``: on sem-nav's route map the stop is masked unless the route's sem-nav faces the target
    it would stop beside; the other actions always stay. ``allowed_actions`` gives the gate with ``STOP_AT``, and no
    mask and no ``stop_at`` to a policy without the route map (it stops only where the stop is most likely)."""
    from types import SimpleNamespace

    from agents.imitation import _policy_step
    from agents.maps import STOP_AT, allowed_actions, stop_gate
    from agents.navmap import NavEgoMap, RouteNavMap2

    _, m, stop, obs = _policy_with_a_stop(3.0)  # the stop by far the most likely action
    ego = RouteNavMap2.__new__(RouteNavMap2)
    ego.teacher = SimpleNamespace(mode="explore")
    gate = stop_gate(m, ego)
    assert not gate[stop] and gate.sum() == len(gate) - 1
    allowed, stop_at = allowed_actions(m, ego)
    assert stop_at == STOP_AT and np.array_equal(allowed, gate)
    rng = np.random.default_rng(3)
    drawn = [_policy_step(m, obs, m.initial_state(1), True, rng, allowed=allowed, stop_at=stop_at)[0]
             for _ in range(50)]
    assert all(a[2] < 0 for a in drawn)  # exploring: never the stop, however likely
    ego.teacher.mode = "face"
    allowed, stop_at = allowed_actions(m, ego)
    assert allowed.all()
    assert _policy_step(m, obs, m.initial_state(1), True, rng, allowed=allowed, stop_at=stop_at)[0][2] > 0
    assert allowed_actions(m, NavEgoMap()) == (None, None) and allowed_actions(m, None) == (None, None)
    assert allowed_actions(m, ego, stop_at=None) == (None, None)  # the rule before the gate: no mask


def test_with_the_gate_open_a_stop_below_stop_at_is_drawn_at_its_own_odds():
    """Where the stop gate lets the stop through (sem-nav faces its target) and its probability is below ``stop_at``,
    the stop is drawn from the policy's distribution as every other action (session 70): over 3,000 draws at
    p = 0.05 the share of stops lies within 4 standard errors of 0.05. With the gate shut, or without a gate
    (``stop_at`` None, the rule before it), it is never drawn."""
    from types import SimpleNamespace

    from agents.imitation import _policy_step
    from agents.maps import allowed_actions
    from agents.navmap import RouteNavMap2

    _, m, stop, obs = _policy_with_a_stop(0.0, 2.0)  # straight ahead the most likely
    with torch.no_grad():  # the stop at 0.05 of the mass, below STOP_AT
        logits = m.actor.bias.detach().double().clone()
        rest = torch.logsumexp(torch.cat([logits[:stop], logits[stop + 1:]]), 0)
        m.actor.bias[stop] = float(rest + np.log(0.05 / 0.95))
    p_stop = float(torch.softmax(m.actor.bias.detach().double(), 0)[stop])
    assert abs(p_stop - 0.05) < 1e-6
    ego = RouteNavMap2.__new__(RouteNavMap2)
    ego.teacher = SimpleNamespace(mode="face")
    allowed, stop_at = allowed_actions(m, ego)
    assert allowed[stop] and stop_at > p_stop
    rng, n = np.random.default_rng(4), 3000
    h0 = m.initial_state(1)
    share = np.mean([_policy_step(m, obs, h0, True, rng, allowed=allowed, stop_at=stop_at)[0][2] > 0 for _ in range(n)])
    assert abs(share - p_stop) < 4 * np.sqrt(p_stop * (1 - p_stop) / n), share
    ego.teacher.mode = "approach"
    allowed, stop_at = allowed_actions(m, ego)
    assert not any(_policy_step(m, obs, h0, True, rng, allowed=allowed, stop_at=stop_at)[0][2] > 0 for _ in range(300))
    every = np.ones(len(allowed), bool)
    assert not any(_policy_step(m, obs, h0, True, rng, allowed=every)[0][2] > 0 for _ in range(300))


def test_the_routes_sem_nav_counts_itself_beside_its_target_near_it_not_only_on_its_approach_cell():
    """``SemNavAgent._beside`` (the route map's teacher, ``RouteNavMap.BESIDE_M`` 0.3 m): a robot the policy pinned
    against its target an arm's length from the approach cell, or standing at a shower whose sighted floor holds the
    approach cell, is beside it; one 0.1 m farther than the approach cell's gap plus the tolerance is not. sem-nav
    driving itself (``BESIDE_M`` None) and tasks without a stop action (AudioGoal) arrive only on the approach cell."""
    from agents.navmap import RouteNavMap
    from agents.semnav import SemNavAgent

    assert SemNavAgent.BESIDE_M is None and RouteNavMap.BESIDE_M == 0.3
    ag = SemNavAgent.__new__(SemNavAgent)
    ag.BESIDE_M, ag.stop_dim = 0.3, True
    cells = np.array([[1.0, y] for y in np.arange(-0.5, 0.51, 0.1)])  # a sofa's edge along x = 1
    ag.target = (np.array([0.45, 0.6]), cells)  # its approach cell 0.55 m from it (off to the side)
    assert ag._beside(np.array([0.4, 0.0]))  # 0.6 m: the approach cell's 0.55 + 0.1 covers it
    assert not ag._beside(np.array([0.3, 0.0]))  # 0.7 m
    ag.target = (np.array([1.0, 0.0]), cells)  # a shower: the approach cell on its sighted floor
    assert ag._beside(np.array([0.75, 0.3])) and not ag._beside(np.array([0.65, 0.3]))  # 0.25 and 0.35 m
    ag.stop_dim = False
    assert not ag._beside(np.array([0.75, 0.3]))
    ag.stop_dim, ag.BESIDE_M = True, None
    assert not ag._beside(np.array([0.75, 0.3]))


def test_ppo_draws_through_the_floor_shield_and_scores_what_it_drew_under_it():
    """PPO's policy distribution under the floor shield's mask (a map policy fine-tuned as it plays): a forbidden
    action is never drawn, the allowed ones keep their relative odds (log-probabilities renormalised over them),
    and a row that forbids everything keeps every action, as the player does."""
    from agents.models import primitives_for
    from agents.ppo import _dist_of

    m = AVNav(AVNavConfig(primitives=primitives_for(2))).eval()
    logits = torch.log(torch.tensor([[0.4, 0.3, 0.2, 0.1] + [1e-3] * 12]))
    allowed = torch.zeros(1, 16, dtype=torch.bool)
    allowed[0, [1, 3]] = True
    pi = _dist_of(m, logits, allowed)
    torch.manual_seed(0)
    draws = pi.sample((4000,))[:, 0]
    assert set(draws.tolist()) == {1, 3}
    assert abs(float((draws == 1).float().mean()) - 0.75) < 0.03  # 0.3 / (0.3 + 0.1), 4 standard errors
    assert torch.allclose(pi.log_prob(torch.tensor([1])), torch.log(torch.tensor([0.75])), atol=1e-5)
    free = _dist_of(m, logits, torch.zeros(1, 16, dtype=torch.bool))  # nothing allowed: nothing removed
    assert torch.allclose(free.probs, _dist_of(m, logits).probs)
