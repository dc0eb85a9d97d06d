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
