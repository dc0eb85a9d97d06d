"""Progress of long work (bakes, evaluations, benchmarks): a tqdm bar on an interactive terminal; elsewhere (a log
file, CI, a pipe) a log line at each quarter, so logs never fill with carriage returns. tqdm loads lazily."""
from __future__ import annotations

import logging
import sys

log = logging.getLogger("sonicverse.progress")


def progress(iterable, total: int | None = None, desc: str = "", enabled: bool = True):
    """Yield from ``iterable`` while showing progress on stderr (nothing when ``enabled`` is False)."""
    if total is None and hasattr(iterable, "__len__"):
        total = len(iterable)
    if not enabled:
        yield from iterable
        return
    if sys.stderr.isatty():
        from tqdm import tqdm

        yield from tqdm(iterable, total=total, desc=desc, leave=False, dynamic_ncols=True)
        return
    marks = {max(1, round(total * q)) for q in (0.25, 0.5, 0.75, 1.0)} if total else set()
    for i, item in enumerate(iterable, 1):
        yield item
        if i in marks:
            log.info("%s: %d/%d", desc, i, total)
