"""The embodied world: a differential-drive robot in a scene with doors and objects it can carry."""
from sonicverse_core.world.robot import RobotConfig
from sonicverse_core.world.world import World

__all__ = ["RobotConfig", "World"]
