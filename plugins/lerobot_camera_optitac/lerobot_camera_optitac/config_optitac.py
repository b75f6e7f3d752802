"""The configuration of an OptiTac camera, registered in LeRobot's camera configs as ``optitac``."""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.cameras.configs import CameraConfig

#: The side of the tactile image, px (LeRobot's image features; tactile encoders such as Sparsh take 224).
SIDE = 224


@CameraConfig.register_subclass("optitac")
@dataclass(kw_only=True)
class OptiTacCameraConfig(CameraConfig):
    """One OptiTac sensor as a camera of a LeRobot robot.

    Attributes
    ----------
    fps : int
        The rate LeRobot reads the camera at (the dataset's; default 30). The sensor runs at its own rate.
    width, height : int
        224 (the tactile image's side; other values are refused).
    board : str
        optitac-edge's board: a packaged name (``sim``: the built-in simulated sensor) or a board config file.
    sensor : int, optional
        The sensor's id on the board (default: its first).
    cal : str, optional
        A calibration bundle (default: the board's).
    sensor_fps : float, optional
        The sensor camera's frame rate (``camera.fps`` of the board; default the board's).
    scenario : str, optional
        The simulated board's presses: ``presses``, ``slide`` or ``vibrate`` (``[camera.options] scenario``).
    queue_frames : int
        Frames the sensor's camera keeps for its reader (``camera.queue_frames``, 1-16; default 16, the most: a
        recording's reader may fall 16 frames behind, 67 ms at 240 fps, before a frame is dropped, and counted).
    process : bool
        Read the sensor in a process of its own (default; ``open_sensor_process``), so that LeRobot's own threads
        cannot delay its frames; False: in LeRobot's process (``open_sensor``).
    warmup_s : float
        ``connect()`` waits up to this long for the sensor's baseline (its first frames, nothing touching).
    """

    fps: int | None = 30
    width: int | None = SIDE
    height: int | None = SIDE
    board: str = "sim"
    sensor: int | None = None
    cal: str | None = None
    sensor_fps: float | None = None
    scenario: str | None = None
    queue_frames: int = 16
    process: bool = True
    warmup_s: float = 10.0

    def __post_init__(self) -> None:
        if self.width != SIDE or self.height != SIDE:
            raise ValueError(f"an OptiTac camera's image is {SIDE}x{SIDE}, got {self.width}x{self.height}")
        if self.fps is not None and self.fps <= 0:
            raise ValueError(f"fps must be > 0, got {self.fps}")
        if self.warmup_s < 0:
            raise ValueError(f"warmup_s must be >= 0, got {self.warmup_s}")

    def settings(self) -> dict[str, object]:
        """optitac-edge's board config overrides (``open_sensor(settings=...)``)."""
        out: dict[str, object] = {"camera.queue_frames": self.queue_frames}
        if self.sensor_fps is not None:
            out["camera.fps"] = self.sensor_fps
        if self.scenario is not None:
            out["camera.options.scenario"] = self.scenario
        return out
