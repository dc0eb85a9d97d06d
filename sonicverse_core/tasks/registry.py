"""The one list of tasks. Every task is named here once: its command-line name, its Gymnasium id (embodied tasks),
the class that implements it, the VR frame task that runs it with a person in the loop, the agents that can do it
and the metric keys its evaluation prints. The env registration, ``sonicverse task run``, ``sonicverse eval``,
``sonicverse vr --task`` and the agent factory all read this table; adding a task is one :class:`TaskSpec` here and
one small task class (see :mod:`sonicverse_core.tasks.base`).

Classes are named as ``"module:attribute"`` strings and imported on use, so reading the registry imports nothing
heavy (and the core never imports the app: frame tasks are only named).
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass

from sonicverse_core.errors import ConfigError

NAV_METRICS = ("sr", "spl", "sna", "soft_spl", "distance_to_goal")


@dataclass(frozen=True)
class TaskSpec:
    name: str  # the task's proper name ("AudioGoal", "SpeakerFollowing")
    cli: str  # its command-line name ("audio-goal", "speaker-following")
    kind: str  # "embodied": a Gymnasium env with a robot; "trials": a person (or simulated participant) alone
    impl: str  # "module:Class" of the Task (embodied) or of the trial runner
    agents: tuple  # agent names, the first is the default
    metrics: tuple  # keys of the evaluation's JSON (each {"mean", "ci95", "n"})
    rates: tuple = ()  # the metrics that are success rates (Wilson intervals)
    env_id: str | None = None  # Gymnasium id (embodied tasks)
    frame_task: str | None = None  # "module:Class" of the VR frame task (imported by the app only)
    max_steps: int = 500  # the env's own truncation, also the spec's max_episode_steps
    summary: str = ""

    def load(self):
        return load(self.impl)


def load(ref: str):
    module, attr = ref.split(":")
    return getattr(importlib.import_module(module), attr)


TASKS: dict[str, TaskSpec] = {s.name: s for s in (
    TaskSpec("AudioGoal", "audio-goal", "embodied", "sonicverse_core.tasks.nav:AudioGoal",
             ("oracle", "gan", "gan-itd", "sem-nav", "random", "av-nav", "av-nav-greedy", "savi", "multitask"),
             NAV_METRICS, ("sr",),
             env_id="Sonicverse/AudioGoal-v0",
             summary="go to the sounding object (depth + binaural audio)"),
    TaskSpec("AudioPointGoal", "audio-point-goal", "embodied", "sonicverse_core.tasks.nav:AudioPointGoal",
             ("oracle", "gan", "gan-itd", "random"), NAV_METRICS, ("sr",), env_id="Sonicverse/AudioPointGoal-v0",
             summary="AudioGoal with a GPS + compass pointer to the goal"),
    TaskSpec("SemanticAudioNav", "semantic-audio-nav", "embodied", "sonicverse_core.tasks.nav:SemanticAudioNav",
             ("oracle", "gan", "gan-itd", "sem-nav", "random", "av-nav", "av-nav-greedy", "savi",
              "multitask"), NAV_METRICS, ("sr",), env_id="Sonicverse/SemanticAudioNav-v0",
             summary="the paper's task: RGB-D + audio, the sound stops, stop at the object"),
    TaskSpec("SpeakerFollowing", "speaker-following", "embodied", "sonicverse_core.tasks.following:SpeakerFollowing",
             ("scripted", "oracle", "random", "av-nav"),
             ("time_in_band", "catch_success", "mean_distance_m", "lost_s", "collisions", "time_s"),
             ("catch_success",), env_id="Sonicverse/SpeakerFollowing-v0", max_steps=1200,
             frame_task="app.tasks.in_the_loop:FollowMe",
             summary="follow a person who walks a multi-room route speaking now and then; stop near them at the end"),
    TaskSpec("VoiceRetrieval", "voice-retrieval", "embodied", "sonicverse_core.tasks.retrieval:VoiceRetrieval",
             ("oracle", "scripted", "random"),
             ("sr", "spl", "command_accuracy", "speaker_azimuth_error_deg", "speaker_distance_error_m", "time_s",
              "collisions"),
             ("sr", "command_accuracy"), env_id="Sonicverse/VoiceRetrieval-v0", max_steps=900,
             frame_task="app.tasks.in_the_loop:FetchForMe",
             summary="a person asks for an object by voice; fetch one and put it down within 1 m of them"),
    TaskSpec("OrientationTraining", "orientation-training", "trials",
             "sonicverse_core.tasks.orientation:OrientationTraining", ("simulated",),
             ("azimuth_error_deg", "elevation_error_deg", "front_back_confusion_rate", "response_time_s",
              "walk_success", "path_efficiency", "time_to_target_s"),
             ("front_back_confusion_rate", "walk_success"), frame_task="app.tasks.in_the_loop:OrientationTrials",
             summary="a listener turns to face, or walks to, sounds around them; feedback, blocks, a staircase"),
)}


def task_spec(name: str) -> TaskSpec:
    """A task by its proper name, its command-line name or its Gymnasium id."""
    for s in TASKS.values():
        if name in (s.name, s.cli, s.env_id):
            return s
    raise ConfigError(f"unknown task '{name}'; use one of {', '.join(s.cli for s in TASKS.values())}")


def embodied() -> list[TaskSpec]:
    return [s for s in TASKS.values() if s.kind == "embodied"]


def navigation() -> list[TaskSpec]:
    return [s for s in TASKS.values() if s.metrics == NAV_METRICS]
