"""Agents: scripted baselines (random, oracle, gan) and learned policies (torch)."""
from __future__ import annotations


def make_agent(name: str, rng=None):
    """A scripted agent by name: random, oracle or gan."""
    from agents.scripted import AGENTS
    from sonicverse_core.errors import ConfigError

    if name not in AGENTS:
        raise ConfigError(f"unknown agent '{name}'; use one of {', '.join(AGENTS)}")
    return AGENTS[name](rng)
