"""Learned agents (``av-nav``, ``savi``, ``multitask``) as players of the evaluation harness: a checkpoint's policy acting on the sensors it was trained
on (the harness builds the env with :meth:`AVNavAgent.env_kwargs`), with its GRU state carried through an episode and
each action drawn from the policy with the agent's Generator (discrete head; as Habitat's and SoundSpaces'
evaluations do) or the continuous head's mean. ``av-nav-greedy`` takes the most likely action instead: on the 30
AudioGoal test episodes of the README it reaches 20% SR where drawing reaches 46.7%, because a greedy policy that
meets furniture repeats the same choice and stays stuck. A checkpoint may be an ensemble of av-nav policies
(``sonicverse train --ensemble``; :class:`agents.models.PolicyEnsemble`): the action is then drawn from the mean of
their distributions, each member carrying its own GRU state.

A policy with a map input (the speaker follower) acts through a shield: the actions that, held for ``shield_s``
(0.3 s), would drive the robot off the floor plan's navigable floor (walls, furniture: what the scripted follower
plans on) are removed from its distribution before drawing, unless that leaves none. On the README's 30 test
episodes it took the follower from 50 collisions an episode to 2.8 and its catch success from 76.7% to 96.7%; its
time in band stayed where it was (0.720 against 0.734, paired -0.014 [-0.066, +0.038]).

A policy with a stop action (SemanticAudioNav) that reads sem-nav's route may stop only while the route's sem-nav
faces the target it would stop beside (:func:`agents.maps.stop_gate`), and there stops once the stop's probability
reaches ``stop_at`` (0.1); outside the gate a stop is never drawn by chance (it would end the episode), and policies
without the gate stop only where the stop is their most likely action. Imitation labels the stop once an episode, so
beside the goal it was rarely the most likely action and the robot drove on until it timed out: on the 200 test
episodes the gate and 0.1 took the route av-nav from 34.0% to 37.5% SR, 7 episodes gained and none lost, ``savi``
(since session 69) from 33.0% to 35.0% (4 gained, none lost) and ``multitask`` from 32.0% to 34.5% (6 gained, 1
lost) (README, "When a learned navigator stops"). Since session 70 the route's sem-nav also counts itself arrived
once the robot the policy drives is beside its target (:attr:`agents.navmap.RouteNavMap.BESIDE_M`), not only on its
own approach cell, and with the gate open the stop is also drawn from the policy's distribution, as every other
action is: policies that pinned themselves against the goal, or stood at it with the stop's probability a few
hundredths, until they timed out now stop there: on the 200 test episodes savi 35.0% -> 36.5% (4 gained, 1 lost),
multitask 34.5% -> 36.5% (6 gained, 2 lost), av-nav 37.5% both ways (README). ``stop_at = None`` plays the rule
before the gate."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from agents.maps import SHIELD_S, STOP_AT
from agents.scripted import Agent

CHECKPOINTS = Path(__file__).resolve().parent / "checkpoints"


def default_checkpoint(arch: str, task: str) -> Path:
    return CHECKPOINTS / f"{arch}_{task}.pt"


def check_trained_on(path, meta: dict, task: str) -> None:
    """A checkpoint plays (or fine-tunes on) the task it was trained on: another task's policy would run, with
    the same sensors, and score as if it had been meant for it."""
    from sonicverse_core.errors import ConfigError

    trained = (meta.get("config") or {}).get("task")
    if trained and trained != task:
        raise ConfigError(f"{path} was trained on {trained}, not {task}: give a checkpoint trained on {task}")


class AVNavAgent(Agent):
    name = "av-nav"
    arch = "av-nav"  # the checkpoint's architecture
    # s: a policy that reads the task's floor plan (``--map``) never draws an action that, held this long, would
    # drive it off the plan's navigable floor (:func:`agents.following.floor_safe`); None: no such check
    shield_s: float | None = SHIELD_S
    # a route policy with a stop action (SemanticAudioNav) may stop only while its map's sem-nav faces its target
    # (agents.maps.stop_gate), and there stops once the stop's probability reaches this; None: only where the stop is
    # the most likely action (README "When a learned navigator stops")
    stop_at: float | None = STOP_AT

    def __init__(self, rng: np.random.Generator | None = None, checkpoint=None, task: str = "AudioGoal"):
        super().__init__(rng)
        from agents.models import load_policy

        self.checkpoint = Path(checkpoint) if checkpoint else default_checkpoint(self.arch, task)
        self.model, self.meta = load_policy(self.checkpoint, self.arch)
        check_trained_on(self.checkpoint, self.meta, task)
        self.size = self.model.cfg.depth_hw[0]
        self.sample = True  # draw from the policy (discrete head, the Generator); False: the most likely action
        self.temperature = float(self.meta.get("temperature", 1.0))  # an ensemble's acting setting (its meta)

    def env_kwargs(self) -> dict:
        from agents.maps import sensors_for

        return {"sensors": sensors_for(self.model), "width": self.size, "height": self.size}

    def reset(self, env, obs, info) -> None:
        from agents.maps import ego_for

        super().reset(env, obs, info)
        self.h = self.model.initial_state(1)
        self.start = True
        self.ego = ego_for(self.model)  # a policy with a map input: the map it reads (agents.following.EgoMap)
        if self.ego is not None:
            self.ego.reset(env, obs, info)

    def act(self, obs, info) -> np.ndarray:
        from agents.imitation import _policy_step
        from agents.maps import allowed_actions

        mp = self.ego.observe(obs, info) if self.ego is not None else None
        allowed, stop_at = allowed_actions(self.model, self.ego, self.shield_s, self.stop_at)
        a, self.h = _policy_step(self.model, obs, self.h, self.start, self.rng if self.sample else None, mp,
                                 allowed, self.temperature, stop_at)
        self.start = False
        return np.clip(a, -1, 1).astype(np.float32)


class SAViAgent(AVNavAgent):
    """``savi``: SAVi (:mod:`agents.savi`) acting as ``av-nav`` does: its goal descriptor and scene memory are its
    state through the episode."""

    name = "savi"
    arch = "savi"


class MultitaskAgent(AVNavAgent):
    """``multitask``: SAVi with occupancy anticipation (the paper's model); it acts on the state feature, the map
    is its training's auxiliary task."""

    name = "multitask"
    arch = "multitask"


class AVNavGreedy(AVNavAgent):
    """``av-nav-greedy``: the same policy taking its most likely action at every step."""

    name = "av-nav-greedy"

    def __init__(self, rng=None, checkpoint=None, task: str = "AudioGoal"):
        super().__init__(rng, checkpoint, task)
        self.sample = False
