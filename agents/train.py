"""The entry point ``torchrun`` launches: ``torchrun --nproc_per_node=K [--nnodes N ...] -m agents.train ARGS`` runs
``sonicverse train ARGS`` in every process (ARGS as for ``sonicverse train``; DD-PPO with ``--recipe ppo``)."""
from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    from app.cli import main as cli

    return cli(["train", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
