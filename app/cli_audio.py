"""CLI commands of the acoustic engine (render, bake, bench audio, bench accuracy)."""
from __future__ import annotations


def add_audio_commands(sub, bench_sub) -> None:
    """Registered by app.cli; filled in as the acoustic engine lands."""
    return None
