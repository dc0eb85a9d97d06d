"""Embodied tasks as Gymnasium environments (``Sonicverse/AudioGoal-v0``, ``Sonicverse/AudioPointGoal-v0``,
``Sonicverse/SemanticAudioNav-v0``), episodes and metrics.

Importing this package registers the environments. In a fresh interpreter, name the module in the id and
Gymnasium imports it first: ``gymnasium.make("sonicverse_core.tasks:Sonicverse/AudioGoal-v0")`` (Gymnasium 1.x does
not load entry points, so ``gymnasium.make("Sonicverse/AudioGoal-v0")`` works only after ``import
sonicverse_core.tasks``). The spec carries ``max_episode_steps`` = the task's ``max_steps`` (500).
"""
from __future__ import annotations

MAX_STEPS = 500  # TaskConfig.max_steps: the env truncates itself there too

ENV_IDS = {"AudioGoal": "Sonicverse/AudioGoal-v0", "AudioPointGoal": "Sonicverse/AudioPointGoal-v0",
           "SemanticAudioNav": "Sonicverse/SemanticAudioNav-v0"}


def register_envs() -> None:
    import gymnasium as gym

    for task, env_id in ENV_IDS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=f"sonicverse_core.tasks.nav:{task}Env", max_episode_steps=MAX_STEPS,
                         disable_env_checker=True)


register_envs()


class EnvFactory:
    """A picklable ``() -> env`` for vector-env workers: registers the ids inside the worker, then makes the env
    (the camera's GL context is created there, on the first reset)."""

    def __init__(self, task: str, **kwargs):
        if task not in ENV_IDS:
            from sonicverse_core.errors import ConfigError

            raise ConfigError(f"unknown task '{task}'; use one of {', '.join(ENV_IDS)}")
        self.task, self.kwargs = task, kwargs

    def __call__(self):
        import gymnasium as gym

        register_envs()
        return gym.make(ENV_IDS[self.task], **self.kwargs)


def make_vector_env(task: str, num_envs: int, context: str = "forkserver", **kwargs):
    """``num_envs`` environments in subprocess workers (Gymnasium AsyncVectorEnv, NEXT_STEP autoreset)."""
    import gymnasium as gym

    return gym.vector.AsyncVectorEnv([EnvFactory(task, **kwargs) for _ in range(num_envs)], context=context,
                                     autoreset_mode=gym.vector.AutoresetMode.NEXT_STEP)
