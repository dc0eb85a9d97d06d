"""Agents: scripted baselines (random, oracle, gan and gan-itd, the semantic navigator sem-nav, the speaker followers)
and learned policies (torch).

The registry (:mod:`sonicverse_core.tasks.registry`) says which agent names a task takes; this table says which
class plays each (name, task).
"""
from __future__ import annotations

_LEARNED = {"av-nav": "agents.learned:AVNavAgent", "av-nav-greedy": "agents.learned:AVNavGreedy",
            "savi": "agents.learned:SAViAgent", "multitask": "agents.learned:MultitaskAgent"}
_NAV = {"random": "agents.scripted:RandomAgent", "oracle": "agents.scripted:OracleAgent",
        "gan": "agents.gan:GanAgent", "gan-itd": "agents.scripted:GanItdAgent",
        "sem-nav": "agents.semnav:SemNavAgent", **_LEARNED}
# agents that load a checkpoint (``checkpoint=``; default agents/checkpoints/ARCH_TASK.pt)
LEARNED = {"av-nav", "av-nav-greedy", "savi", "multitask"}
IMPLEMENTATIONS = {
    "AudioGoal": _NAV, "AudioPointGoal": _NAV, "SemanticAudioNav": _NAV,
    "SpeakerFollowing": {"random": "agents.scripted:RandomAgent", "oracle": "agents.following:OracleFollower",
                         "scripted": "agents.following:MapFollower", **_LEARNED},
    "VoiceRetrieval": {"random": "agents.scripted:RandomAgent", "oracle": "agents.retrieval:OracleRetriever",
                       "scripted": "agents.retrieval:ScriptedRetriever"},
}


def check_agent(name: str, task: str, checkpoint=None) -> None:
    """A ConfigError unless ``name`` can play ``task``: one the registry lists for it, a learned one given a
    ``checkpoint`` (a task it has no shipped one for), or ``module:callable``; ``checkpoint`` only for learned ones."""
    from sonicverse_core.errors import ConfigError
    from sonicverse_core.tasks.registry import task_spec

    spec = task_spec(task)
    if checkpoint is not None and name not in LEARNED:
        raise ConfigError(f"--checkpoint is for learned agents ({', '.join(sorted(LEARNED))}), not '{name}'")
    if ":" in name:
        return
    listed = name in spec.agents or (name in LEARNED and checkpoint is not None)
    if not listed or name not in IMPLEMENTATIONS.get(spec.name, {}):
        raise ConfigError(f"unknown agent '{name}' for {spec.cli}; use one of {', '.join(spec.agents)} "
                          "(or module:callable)")


def make_agent(name: str, rng=None, task: str = "AudioGoal", checkpoint=None):
    """The agent ``name`` for ``task`` (a name, command-line name or id from the registry), or a user's own policy
    given as ``module:callable`` (called with the Generator; it must offer ``reset(env, obs, info)`` and
    ``act(obs, info)``, and may offer ``env_kwargs()``). Learned agents load ``checkpoint`` (default: the shipped
    one for the task)."""
    from sonicverse_core.errors import ConfigError
    from sonicverse_core.tasks.registry import load, task_spec

    spec = task_spec(task)
    if ":" in name:
        try:
            return load(name)(rng)
        except (ImportError, AttributeError, ValueError) as exc:
            raise ConfigError(f"cannot load agent '{name}': {exc}") from None
    check_agent(name, spec.name, checkpoint)
    impl = IMPLEMENTATIONS[spec.name]
    if name in LEARNED:
        return load(impl[name])(rng, checkpoint=checkpoint, task=spec.name)
    return load(impl[name])(rng)
