"""Agents: scripted baselines (random, oracle, gan, the speaker followers) and learned policies (torch).

The registry (:mod:`sonicverse_core.tasks.registry`) says which agent names a task takes; this table says which
class plays each (name, task).
"""
from __future__ import annotations

_NAV = {"random": "agents.scripted:RandomAgent", "oracle": "agents.scripted:OracleAgent",
        "gan": "agents.scripted:GanAgent"}
IMPLEMENTATIONS = {
    "AudioGoal": _NAV, "AudioPointGoal": _NAV, "SemanticAudioNav": _NAV,
    "SpeakerFollowing": {"random": "agents.scripted:RandomAgent", "oracle": "agents.following:OracleFollower",
                         "scripted": "agents.following:MapFollower"},
    "VoiceRetrieval": {"random": "agents.scripted:RandomAgent", "oracle": "agents.retrieval:OracleRetriever",
                       "scripted": "agents.retrieval:ScriptedRetriever"},
}


def make_agent(name: str, rng=None, task: str = "AudioGoal"):
    """The agent ``name`` for ``task`` (a name, command-line name or id from the registry)."""
    from sonicverse_core.errors import ConfigError
    from sonicverse_core.tasks.registry import load, task_spec

    spec = task_spec(task)
    impl = IMPLEMENTATIONS.get(spec.name, {})
    if name not in spec.agents or name not in impl:
        raise ConfigError(f"unknown agent '{name}' for {spec.cli}; use one of {', '.join(spec.agents)}")
    return load(impl[name])(rng)
