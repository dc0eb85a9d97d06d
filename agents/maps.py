"""Which sensors and which egocentric map a learned policy reads, the shield it acts through and where it may stop:
one place for what training (:mod:`agents.imitation`, :mod:`agents.ppo`) and playing (:mod:`agents.learned`) must
agree on.

A policy's ``map_kind`` (its config's, when it has a map input) names its map: "follow" the speaker follower's
:class:`agents.following.EgoMap` (from the task's floor plan), "nav" :class:`agents.navmap.NavEgoMap` (from depth,
sound and odometry), "sem" :class:`agents.navmap.SemNavMap` (that and the named category's sightings), "route2"
:class:`agents.navmap.RouteNavMap2` (that and the way sem-nav would go now: what ``train --map route`` trains) and
"route" :class:`agents.navmap.RouteNavMap` (the same drawn by sem-nav before session 55, as the files trained before
session 56 read it).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from agents.imitation import ImitationConfig

SENSORS = ("depth", "spectrogram", "pose")
MAP_SENSORS = SENSORS + ("audio",)  # a policy with a map input: EgoMap listens to the raw block


MAP_TASKS = {"SpeakerFollowing": "follow", "AudioGoal": "nav", "SemanticAudioNav": "sem"}  # train --map: which map
ROUTE_TASKS = ("AudioGoal", "SemanticAudioNav")  # train --map route: sem-nav's route drawn in (RouteNavMap2)
ROUTE_KINDS = ("route", "route2")  # the map kinds with sem-nav's route drawn in
#: the env sensors sem-nav acts on (SemNavExpert, RouteNavMap)
SEMNAV_SENSORS = ("depth", "semantic", "spectrogram", "audio", "pose", "bump")
#: the env sensors a policy with each kind of map acts on (EgoMap listens to the raw block; SemNavMap reads the
#: semantic camera, and its teacher, sem-nav, the raw block; RouteNavMap runs sem-nav every step)
MAP_KIND_SENSORS = {"follow": MAP_SENSORS, "nav": SENSORS, "sem": SENSORS + ("semantic", "audio"),
                    "route": SEMNAV_SENSORS, "route2": SEMNAV_SENSORS}


def _map_kind(model) -> str | None:
    return getattr(model.cfg, "map_kind", "follow") if getattr(model.cfg, "map_shape", ()) else None


def sensors_for(model) -> tuple:
    """The env sensors ``model`` acts on."""
    return MAP_KIND_SENSORS.get(_map_kind(model), SENSORS)


def map_class(kind: str):
    """The map class a ``map_kind`` names (the module's docstring lists them)."""
    if kind == "follow":
        from agents.following import EgoMap

        return EgoMap
    from agents.navmap import NavEgoMap, RouteNavMap, RouteNavMap2, SemNavMap

    return {"sem": SemNavMap, "route": RouteNavMap, "route2": RouteNavMap2}.get(kind, NavEgoMap)


def ego_for(model):
    """The egocentric map a policy with a map input reads (None for the others)."""
    kind = _map_kind(model)
    return None if kind is None else map_class(kind)()


SHIELD_S = 0.3  # s: the floor shield's horizon (agents.learned.AVNavAgent.shield_s)
#: a route policy with a stop action stops, where :func:`stop_gate` lets it, once the stop's probability reaches this
#: (agents.learned.AVNavAgent.stop_at; README "When a learned navigator stops")
STOP_AT = 0.1


def floor_shield(model, ego, horizon_s: float | None = SHIELD_S):
    """The actions a discrete policy that reads the task's floor plan (:class:`agents.following.EgoMap`) may take
    now: those that, held for ``horizon_s``, keep it on the plan's navigable floor
    (:func:`agents.following.floor_safe`); None (no restriction) for other policies or without a horizon. Call it
    after ``ego.observe`` (which moves the map's robot to this step's pose)."""
    from agents.following import EgoMap, floor_safe

    if not horizon_s or not model.discrete or not isinstance(ego, EgoMap):
        return None
    return floor_safe(model.table.cpu().numpy(), ego.map.grid, ego.me.pose, ego.robot, horizon_s)


def stop_gate(model, ego):
    """The actions a policy with a stop action (SemanticAudioNav) that reads sem-nav's route
    (:class:`agents.navmap.RouteNavMap`) may take now: every one but the stop, which only while the route's sem-nav
    faces the target it would stop beside (the map then draws the line to it; it turns to face it on its approach cell
    or, since session 70, wherever the robot is beside it: ``RouteNavMap.BESIDE_M``); None (no restriction) for other
    policies. Where it lets the stop through, the stop is taken at ``STOP_AT`` and else drawn at its own odds
    (:func:`agents.imitation._policy_step`). Call it after ``ego.observe``."""
    from agents.navmap import RouteNavMap

    if not model.discrete or not isinstance(ego, RouteNavMap) or model.table.shape[1] != 3:
        return None
    stop = model.table[:, 2].cpu().numpy() > 0
    return ~stop | (ego.teacher.mode == "face")


def allowed_actions(model, ego, shield_s: float | None = SHIELD_S, stop_at: float | None = STOP_AT):
    """(the actions a policy may take now, the stop's probability that makes it stop) as it plays: the floor
    shield's (:func:`floor_shield`) or, given ``stop_at``, the stop gate's (:func:`stop_gate`) mask, None where
    neither applies; ``stop_at`` where the gate applies, else None (a stop only where it is the most likely action)."""
    shield = floor_shield(model, ego, shield_s)
    gate = None if stop_at is None else stop_gate(model, ego)
    if gate is None:
        return shield, None
    return (gate if shield is None else gate & shield), stop_at


def map_kind_for(cfg: "ImitationConfig") -> str:
    """The kind of map ``cfg`` trains a policy to read (with ``cfg.egomap``): the task's, or "route2" (the current
    sem-nav's route)."""
    return "route2" if cfg.route else MAP_TASKS.get(cfg.task, "nav")


def collect_sensors(cfg: "ImitationConfig") -> tuple:
    """The env sensors DAgger collects with: the policy's (a map policy's include what its map reads), and sem-nav's
    where it is the teacher without a map."""
    if cfg.egomap:
        return MAP_KIND_SENSORS[map_kind_for(cfg)]
    return SEMNAV_SENSORS if cfg.teacher == "scripted" else SENSORS
