"""The configuration of the OptiTac robot, registered in LeRobot's robot configs as ``optitac``."""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.cameras.configs import CameraConfig
from lerobot.robots.config import RobotConfig
from lerobot_camera_optitac import OptiTacCameraConfig


@RobotConfig.register_subclass("optitac")
@dataclass(kw_only=True)
class OptiTacConfig(RobotConfig):
    """An OptiTac sensor read at its own rate, its newest reading an observation at LeRobot's.

    Attributes
    ----------
    arm : RobotConfig, optional
        The robot the sensor sits on (any LeRobot robot type): its joints, cameras and actions pass through, the
        tactile observations are added beside them. None: the sensor alone (no actions).
    tactile : OptiTacCameraConfig
        The sensor (board, sensor id, bundle, its frame rate, the simulated board's scenario).
    image : bool
        Add the tactile image (224 x 224) as a camera, ``observation.images.optitac``.
    fibers : bool
        Add each fiber's signal to the observations (``optitac.fiber<ID>``; 217 values for the paper's array).
    cameras : dict
        Cameras of the sensor's own robot (with no arm), as any LeRobot robot's.
    """

    arm: RobotConfig | None = None
    tactile: OptiTacCameraConfig = field(default_factory=OptiTacCameraConfig)
    image: bool = True
    fibers: bool = False
    cameras: dict[str, CameraConfig] = field(default_factory=dict)
