"""Scheduling of the live pipeline's threads: a real-time priority where the machine allows one, else the highest
time-shared priority it allows (a negative nice value), and news of which.

Some machines refuse SCHED_FIFO even to root (a container or VM whose real-time budget is zero; the lent machines
of README's "Benchmarks" did). A time-shared thread at nice -20 still gets about 87 times the CPU share of one at
nice 0 under contention (the kernel's weight table: 88761 against 1024), so the callback, the supervisor, the
robots' renderer and the JACK server's threads are niced where FIFO is refused (``SONICVERSE_RT_NICE`` picks
which). On a lent machine so niced (README "Benchmarks", session 38) every task played 60 s at 512 frames with no
xrun; session 37's A/B against no nice at all was within the machines' spread. Where neither is allowed the thread
runs as it was, and the news says so: never a silent fallback.
"""
from __future__ import annotations

import os
import threading

# the time-shared fallback's nice values, in the order of the real-time priorities they stand for: the callback
# (the audio server's client thread) above the supervisor above the robots' renderer
NICE_CALLBACK = -20
NICE_SUPERVISOR = -15
NICE_ROBOTS = -10
NICE_SERVER = -20

ROLES = ("callback", "supervisor", "robots", "server")


def nice_roles() -> frozenset:
    """The threads that take the time-shared fallback: ``SONICVERSE_RT_NICE`` (a comma-separated subset of
    callback, supervisor, robots, server; 'none' for none), all of them when unset."""
    v = os.environ.get("SONICVERSE_RT_NICE")
    if v is None:
        return frozenset(ROLES)
    got = frozenset(r.strip() for r in v.split(",") if r.strip() and r.strip() != "none")
    bad = got - set(ROLES)
    if bad:
        from sonicverse_core.errors import ConfigError

        raise ConfigError(f"SONICVERSE_RT_NICE: unknown thread role(s) {sorted(bad)}; known: {', '.join(ROLES)}, "
                          "or none")
    return got


TIME_SHARED = frozenset(getattr(os, n) for n in ("SCHED_OTHER", "SCHED_BATCH", "SCHED_IDLE") if hasattr(os, n))


def renice(tid: int, nice: int) -> int | None:
    """Set thread ``tid``'s nice value (Linux: per thread); the value it has afterwards, or None when refused."""
    try:
        os.setpriority(os.PRIO_PROCESS, tid, nice)
        return os.getpriority(os.PRIO_PROCESS, tid)
    except (OSError, AttributeError):
        return None


def favour_this_thread(prio: int, nice: int, role: str) -> str:
    """Run the calling thread at SCHED_FIFO ``prio`` where allowed; else at nice ``nice`` where allowed; else as it
    is. Says which: 'SCHED_FIFO 4', 'time-shared, nice -15 (SCHED_FIFO refused: ...)' or 'time-shared, nice 0
    (SCHED_FIFO refused: ...; nice -15 refused)'."""
    try:
        prio = max(1, min(prio, os.sched_get_priority_max(os.SCHED_FIFO)))
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
        return f"SCHED_FIFO {prio}"
    except (OSError, AttributeError) as exc:
        why = f"SCHED_FIFO refused: {getattr(exc, 'strerror', None) or exc}"
    tid = threading.get_native_id()
    if role not in nice_roles():
        return f"time-shared, nice {thread_nice(tid)} ({why}; no nice asked: SONICVERSE_RT_NICE)"
    got = renice(tid, nice)
    if got is None:
        return f"time-shared, nice {thread_nice(tid)} ({why}; nice {nice} refused)"
    return f"time-shared, nice {got} ({why})"


def favour_if_time_shared(nice: int, role: str = "callback") -> tuple[int, int, int]:
    """For a thread whose scheduling someone else chose (the audio server's client thread, which runs the stream's
    callback): when it is time-shared, raise its time-shared priority to ``nice`` where allowed. Returns (policy,
    real-time priority, nice value) as they are afterwards (the telemetry's news)."""
    policy = os.sched_getscheduler(0)
    tid = threading.get_native_id()
    if policy in TIME_SHARED and role in nice_roles():
        renice(tid, nice)
    return policy, os.sched_getparam(0).sched_priority, thread_nice(tid)


def favour_process_threads(pid: int, nice: int, role: str = "server") -> str:
    """Another process's threads (the JACK server's): those that run time-shared get nice ``nice`` where allowed.
    Says what its threads run at afterwards: 'SCHED_FIFO 10 (2 threads), time-shared nice -20 (3 threads)'."""
    counts: dict[str, int] = {}
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except OSError as exc:
        return f"unknown ({exc.strerror})"
    for tid in tids:
        try:
            policy = os.sched_getscheduler(tid)
            if policy in TIME_SHARED:
                if role in nice_roles():
                    renice(tid, nice)
                key = f"time-shared nice {thread_nice(tid)}"
            else:
                key = f"{'SCHED_FIFO' if policy == os.SCHED_FIFO else f'policy {policy}'} " \
                      f"{os.sched_getparam(tid).sched_priority}"
        except OSError:  # the thread ended meanwhile
            continue
        counts[key] = counts.get(key, 0) + 1
    return ", ".join(f"{k} ({n} thread{'s' if n > 1 else ''})" for k, n in sorted(counts.items()))


def fifo_allowed() -> bool:
    """Whether this machine lets a thread of this process take SCHED_FIFO (tried on a short-lived thread)."""

    def probe():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            return True
        except (OSError, AttributeError):
            return False

    return _on_a_thread(probe)


def nice_allowed(nice: int) -> bool:
    """Whether this machine lets a thread of this process take nice ``nice`` (tried on a short-lived thread)."""
    return _on_a_thread(lambda: renice(threading.get_native_id(), nice) == nice)


def _on_a_thread(fn) -> bool:
    ok = []
    t = threading.Thread(target=lambda: ok.append(fn()), name="sv-sched-probe")
    t.start()
    t.join()
    return ok[0]


def thread_nice(tid: int) -> int:
    """Thread (or process) ``tid``'s nice value; 0 when it cannot be read."""
    try:
        return os.getpriority(os.PRIO_PROCESS, tid)
    except OSError:
        return 0
