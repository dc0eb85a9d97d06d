"""Embodied tasks as Gymnasium environments (``Sonicverse/AudioGoal-v0``, ``Sonicverse/AudioPointGoal-v0``,
``Sonicverse/SemanticAudioNav-v0``), episodes and metrics.

Importing this package registers the environments; Gymnasium also finds them through the ``gymnasium.envs``
entry point, so ``gymnasium.make("Sonicverse/AudioGoal-v0")`` works after ``import gymnasium`` alone.
"""
from __future__ import annotations

ENV_IDS = {"AudioGoal": "Sonicverse/AudioGoal-v0", "AudioPointGoal": "Sonicverse/AudioPointGoal-v0",
           "SemanticAudioNav": "Sonicverse/SemanticAudioNav-v0"}


def register_envs() -> None:
    import gymnasium as gym

    for task, env_id in ENV_IDS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=f"sonicverse_core.tasks.nav:{task}Env", max_episode_steps=None,
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
