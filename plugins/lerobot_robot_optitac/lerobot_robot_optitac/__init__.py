"""An OptiTac sensor's contacts as a LeRobot robot's observations (``type: optitac``), alone or beside an arm.

LeRobot imports this package by its distribution's name (``lerobot_robot_`` prefix), which registers the robot's
config; LeRobot then makes the robot from it by name (``OptiTacConfig`` -> :class:`OptiTac`, in this package).
See docs/lerobot.md of optitac-edge.
"""

from lerobot_robot_optitac.config_optitac import OptiTacConfig
from lerobot_robot_optitac.optitac import OptiTac

__all__ = ["OptiTac", "OptiTacConfig"]
