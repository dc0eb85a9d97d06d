"""Counterbalancing and a session's plan.

A balanced Latin square (Williams 1949) for n conditions: the first row is 0, 1, n-1, 2, n-2, 3, ...; each next
row adds 1 (mod n); for odd n every row is also used reversed (2n rows). Every condition then appears in every
position equally often and follows every other condition equally often, over a multiple of the rows.

Assignment: ``latin`` gives the participant enrolled k-th (1, 2, 3... in order of creation) row (k - 1) mod rows;
``least-filled`` gives the row with the fewest *completed* sessions so far (ties: the lowest row), so dropouts are
refilled.

A session's plan is its list of trial slots, made once when the session is created and stored with it (frozen: a
resume runs the same slots in the same order with the same seeds).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


def williams(n: int) -> list[list[int]]:
    """The rows of a balanced Latin square for n conditions (0-based): n rows for even n, 2n for odd n."""
    if n < 1:
        raise ValueError("need at least one condition")
    first, lo, hi = [0], 1, n - 1
    for k in range(1, n):
        if k % 2:
            first.append(lo)
            lo += 1
        else:
            first.append(hi)
            hi -= 1
    rows = [[(c + r) % n for c in first] for r in range(n)]
    if n % 2:
        rows += [row[::-1] for row in rows]
    return rows


def assign_row(method: str, n_conditions: int, enrol_index: int, completed_per_row: dict | None = None) -> int:
    """Which row of the square a new session gets."""
    rows = len(williams(n_conditions))
    if method == "latin":
        return (enrol_index - 1) % rows
    counts = completed_per_row or {}
    return min(range(rows), key=lambda r: (counts.get(r, 0), r))


@dataclass(frozen=True)
class Slot:
    slot: int  # 0-based position in the session
    block: int  # 0-based block of the session (per-condition blocks expanded)
    block_name: str
    task: str
    condition: str
    trial: int  # within the block, practice trials first (0-based)
    practice: bool
    seed: int

    def as_dict(self) -> dict:
        return asdict(self)


def session_plan(study, order: list[str], participant_enrol: int, session: int) -> list[Slot]:
    """The trial slots of a session: blocks in the study's order, a per-condition block once per condition in
    ``order``; practice trials first in each block; each slot's seed from (study seed, enrolment, session, slot)."""
    slots: list[Slot] = []
    b = 0
    for blk in study.blocks:
        conds = order if blk.per_condition else [blk.condition]
        for cond in conds:
            for t in range(blk.practice + blk.trials):
                k = len(slots)
                seed = int(np.random.SeedSequence([study.seed, participant_enrol, session, k]).generate_state(1)[0])
                slots.append(Slot(k, b, blk.name, blk.task, cond, t, t < blk.practice, seed))
            b += 1
    return slots
