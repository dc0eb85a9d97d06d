"""Embodied tasks as Gymnasium environments, trial tasks for people, episodes and metrics.

Every task is listed once, in :mod:`sonicverse_core.tasks.registry`. Importing this package registers the
environments of the embodied ones (``Sonicverse/AudioGoal-v0``, ``Sonicverse/AudioPointGoal-v0``,
``Sonicverse/SemanticAudioNav-v0``, ``Sonicverse/SpeakerFollowing-v0``). In a fresh interpreter, name the module in
the id and Gymnasium imports it first: ``gymnasium.make("sonicverse_core.tasks:Sonicverse/AudioGoal-v0")``
(Gymnasium 1.x does not load entry points, so ``gymnasium.make("Sonicverse/AudioGoal-v0")`` works only after
``import sonicverse_core.tasks``). Each spec carries ``max_episode_steps`` = the task's ``max_steps`` (the env
truncates itself there too).
"""
from __future__ import annotations

from sonicverse_core.tasks.registry import TASKS, embodied, task_spec

MAX_STEPS = TASKS["AudioGoal"].max_steps

#: task name -> Gymnasium id, for every embodied task
ENV_IDS = {s.name: s.env_id for s in embodied()}


def register_envs() -> None:
    import gymnasium as gym

    for s in embodied():
        if s.env_id not in gym.registry:
            gym.register(id=s.env_id, entry_point="sonicverse_core.tasks.base:TaskEnv", kwargs={"task": s.name},
                         max_episode_steps=s.max_steps, disable_env_checker=True)


register_envs()


def make_env(task: str, **kwargs):
    """The unwrapped env of an embodied task (by name, command-line name or id)."""
    from sonicverse_core.tasks.base import TaskEnv

    return TaskEnv(task=task_spec(task).name, **kwargs)


class EnvFactory:
    """A picklable ``() -> env`` for vector-env workers: registers the ids inside the worker, then makes the env
    (the camera's GL context is created there, on the first reset). ``threads``: the worker's software rasteriser
    (Mesa llvmpipe, ``LP_NUM_THREADS``) and math libraries use that many threads; by default llvmpipe starts one
    per core in every worker, and N workers on N cores then fight over them."""

    def __init__(self, task: str, threads: int | None = None, **kwargs):
        spec = task_spec(task)
        if spec.env_id is None:
            from sonicverse_core.errors import ConfigError

            raise ConfigError(f"task '{spec.cli}' has no Gymnasium env")
        self.task, self.threads, self.kwargs = spec.name, threads, kwargs

    def __call__(self):
        import gymnasium as gym

        if self.threads:
            limit_threads(self.threads)
        register_envs()
        return gym.make(ENV_IDS[self.task], **self.kwargs)


def cores() -> int:
    """The cores this process may run on."""
    import os

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def worker_threads(num_envs: int) -> int:
    """Threads per worker so that ``num_envs`` workers share this machine's cores (at least 1)."""
    return max(1, cores() // max(num_envs, 1))


def exit_with_parent(period_s: float = 0.5) -> None:
    """A spawned worker ends itself when the process that started it is gone (killed with -9, say): a daemon thread
    watches the parent's pid, so no orphan goes on rendering or waits for work forever."""
    import multiprocessing
    import os
    import threading
    import time

    # the pid multiprocessing was started from, not getppid() now: the parent may already be gone by the time
    # the worker gets here (it would then watch its adopter)
    known = multiprocessing.parent_process()
    parent = known.pid if known is not None else os.getppid()

    def watch():
        while os.getppid() == parent:
            time.sleep(period_s)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def limit_threads(n: int) -> None:
    """A worker process's software rasteriser (Mesa llvmpipe) and math libraries use ``n`` threads: set before
    they start (the first GL context, the first numba or BLAS call)."""
    import os

    for k in ("LP_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[k] = str(n)


def make_vector_env(task: str, num_envs: int, context: str = "forkserver", threads: int | None = -1, **kwargs):
    """``num_envs`` environments in subprocess workers (Gymnasium AsyncVectorEnv, NEXT_STEP autoreset).
    ``threads``: per worker (see :class:`EnvFactory`); -1 (default) shares the cores out (:func:`worker_threads`),
    None leaves the libraries' defaults."""
    import gymnasium as gym

    t = worker_threads(num_envs) if threads == -1 else threads
    return gym.vector.AsyncVectorEnv([EnvFactory(task, threads=t, **kwargs) for _ in range(num_envs)],
                                     context=context, autoreset_mode=gym.vector.AutoresetMode.NEXT_STEP)
