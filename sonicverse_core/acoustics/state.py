"""The renderer's subsystems and their per-listener state.

A subsystem is one stage of the block's signal flow: occlusion, propagation paths, the direct sound, early
reflections, late reverb. Each follows one protocol (:class:`Subsystem`):

* ``state(cap)``: a new listener's state for it, a small typed object (a :class:`PerSource` subclass with slots:
  a misspelt field is an error, not a new key) with rows for ``cap`` sources;
* ``grow(state, cap)``: room for more sources, the rows there were kept (``state`` None: the subsystem's own
  per-source arrays, shared by the listeners);
* ``max_delay()``: how far back in the sources' history ring it reads, in seconds (the ring is as long as the
  largest);
* ``render(state, ls, lis, out)``: one block for listener ``lis`` (its :class:`ListenerState` ``ls``): the
  geometry stages (occlusion, paths) refine what the later ones use (``ls.occ_target``, ``ls.pos``, ``ls.fwd``), the
  sound stages add into ``out`` (2, block);
* ``reset(state)``: clear what carries a non-finite block into later ones (filter histories, reverb states).

:func:`sonicverse_core.acoustics.renderer.build_subsystems` builds the list for a scene and leaves out what it
does not need (no occlusion without geometry that can occlude, no paths without a corner to go round, no reflections
or reverb without probes of an enclosed, not fully absorbing space).
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from sonicverse_core.acoustics.sources import grown
from sonicverse_core.scene.materials import BANDS


class PerSource:
    """State with a row per source slot. ``ROWS`` (or the ``rows`` given) lists (name, trailing shape, dtype,
    fill); :meth:`grow` resizes them all, keeping the rows there were."""

    __slots__ = ("_rows",)
    ROWS: tuple = ()

    def __init__(self, cap: int, rows: tuple | None = None):
        self._rows = self.ROWS if rows is None else rows
        self.grow(cap)

    def grow(self, cap: int) -> None:
        for name, shape, dtype, fill in self._rows:
            setattr(self, name, grown(getattr(self, name, None), (cap, *shape), dtype, fill))


class ListenerState(PerSource):
    """What a listener's subsystems share: the output block, the head rotation, the limiter's gain; per source
    whether it is new (``fresh``: filters start where they are, no ramp), unheard (``mute``), and its per-band
    amplitude through walls (``occ_target`` as cast, ``occ`` smoothed across blocks). Per block: ``n`` sources,
    the emitters ``pos``, ``fwd`` (the sources, or where their paths put them), the per-band target ``target`` and
    how much of the last block's amplitude it keeps (``smoothing``). Each
    subsystem's own state is in ``parts`` (aligned with the renderer's ``parts``) and by name (``direct``,
    ``occlusion``, ``paths``, ``early``, ``late``; None when the renderer has no such subsystem)."""

    __slots__ = ("out", "R", "limit", "any_fresh", "fresh", "mute", "occ", "occ_target", "parts", "n", "pos", "fwd",
                 "target", "smoothing", "direct", "occlusion", "paths", "early", "late")
    ROWS = (("fresh", (), bool, True), ("mute", (), bool, False),
            ("occ", (len(BANDS),), np.float64, 1.0), ("occ_target", (len(BANDS),), np.float64, 1.0))

    def __init__(self, cap: int, block: int):
        super().__init__(cap)
        self.out = np.zeros((2, block))
        self.R = np.eye(3)
        self.limit = 1.0
        self.any_fresh = True
        self.parts: tuple = ()
        self.n = 0
        self.pos = self.fwd = self.target = None
        self.smoothing = 0.0
        self.direct = self.occlusion = self.paths = self.early = self.late = None


class Subsystem(Protocol):
    """One stage of the renderer's block (see the module's docstring)."""

    name: str  # the attribute of :class:`ListenerState` that holds its state

    def state(self, cap: int) -> PerSource: ...

    def grow(self, state: PerSource | None, cap: int) -> None: ...

    def max_delay(self) -> float: ...

    def render(self, state: PerSource, ls: ListenerState, lis, out: np.ndarray) -> None: ...

    def reset(self, state: PerSource) -> None: ...
