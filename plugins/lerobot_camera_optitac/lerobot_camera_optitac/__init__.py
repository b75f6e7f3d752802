"""An OptiTac tactile sensor as a LeRobot camera (``type: optitac``).

LeRobot imports this package by its distribution's name (``lerobot_camera_`` prefix) before it reads a command's
configuration, which registers the camera's config; LeRobot then makes the camera from it by name
(``OptiTacCameraConfig`` -> :class:`OptiTacCamera`, in this package). See docs/lerobot.md of optitac-edge.
"""

from lerobot_camera_optitac.config_optitac import OptiTacCameraConfig
from lerobot_camera_optitac.optitac_camera import OptiTacCamera

__all__ = ["OptiTacCamera", "OptiTacCameraConfig"]
