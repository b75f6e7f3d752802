"""An OptiTac sensor as a LeRobot camera: the tactile surface as a 224 x 224 RGB image.

The sensor is opened through optitac-edge's public API, in a process of its own by default
(``open_sensor_process``: LeRobot's threads, encoding video and writing the dataset, cannot hold its frames back;
``process=False``: ``open_sensor``, in LeRobot's process), and read in its own background thread
(``start``) at the sensor's rate; LeRobot takes the newest reading at its own rate. Every sensor frame is
either taken or counted (``status().unread``); frames the sensor's camera lost are counted too
(``status().dropped``), and :attr:`OptiTacCamera.taken` counts the images LeRobot got.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from lerobot.cameras.camera import Camera
from lerobot.utils.errors import DeviceAlreadyConnectedError, DeviceNotConnectedError

import optitac_edge as ot
from lerobot_camera_optitac.config_optitac import OptiTacCameraConfig
from optitac_edge.devtools.lerobot_features import surface_image

#: ``connect()`` returns once a reading is at most this many frame periods old (the camera's queue holds up to
#: 16: a reader within 4 of the newest frame has caught up and has the queue's slack ahead of it).
CAUGHT_UP_FRAMES = 4


class OptiTacCamera(Camera):
    """LeRobot's camera contract over one OptiTac sensor (``connect``, ``read``, ``async_read``,
    ``read_latest``, ``disconnect``)."""

    def __init__(self, config: OptiTacCameraConfig) -> None:
        super().__init__(config)
        self.config = config
        self.sensor: ot.Sensor | ot.SensorProcess | None = None
        self._last: tuple[np.ndarray, int] | None = None  # the newest image and its capture time (ns)
        #: The reading of the image returned last (the robot plugin reads its numbers from it).
        self.last_reading: ot.Reading | None = None
        #: Images returned to LeRobot.
        self.taken = 0

    def __str__(self) -> str:
        return f"OptiTacCamera({self.config.board}, sensor {self.config.sensor})"

    @property
    def is_connected(self) -> bool:
        return self.sensor is not None

    @staticmethod
    def find_cameras() -> list[dict[str, Any]]:
        """optitac-edge's packaged boards (each with its sensors, as ``board`` of the config)."""
        from optitac_edge.config.files import available_boards

        return [{"type": "optitac", "id": name, "name": f"optitac-edge board {name}"} for name in available_boards()]

    def connect(self, warmup: bool = True) -> None:
        """Open the sensor and read it in the background; with ``warmup``, wait until its baseline is ready and
        its reader has caught up with the camera (a reading at most :data:`CAUGHT_UP_FRAMES` frame periods old:
        the frames the camera made while the sensor was opening are behind it, dropped and counted, before
        LeRobot's first frame).

        Raises
        ------
        DeviceAlreadyConnectedError
        ConnectionError
            The sensor cannot be opened, or is not ready and caught up within ``warmup_s`` (one line).
        """
        if self.sensor is not None:
            raise DeviceAlreadyConnectedError(f"{self} is already connected")
        c = self.config
        try:
            opener = ot.open_sensor_process if c.process else ot.open_sensor
            sensor = opener(c.board, sensor=c.sensor, cal=c.cal, settings=c.settings(), arrays=True)
        except ot.OptiTacError as exc:
            raise ConnectionError(f"{self}: {exc}") from None
        sensor.start()
        self.sensor = sensor
        if warmup:
            caught_up_ns = CAUGHT_UP_FRAMES * 1e9 / sensor.status().fps
            deadline = time.monotonic() + c.warmup_s
            while (reading := sensor.latest(timeout_s=max(deadline - time.monotonic(), 0.0))) is not None:
                self._keep(reading)
                if reading.baseline_ready and time.monotonic_ns() - reading.t_ns <= caught_up_ns:
                    return
            self.disconnect()
            raise ConnectionError(f"{self}: no ready baseline within {c.warmup_s:g} s, or the sensor did not "
                                  "keep up with its camera")

    def _sensor(self) -> ot.Sensor | ot.SensorProcess:
        if self.sensor is None:
            raise DeviceNotConnectedError(f"{self} is not connected. Run `.connect()` first.")
        return self.sensor

    def _keep(self, reading: ot.Reading) -> np.ndarray:
        assert reading.surface is not None  # opened with arrays=True
        image = surface_image(reading.surface)  # as export-lerobot --video
        self._last = (image, reading.t_ns)
        self.last_reading = reading
        return image

    def async_read(self, timeout_ms: float = 200) -> np.ndarray:
        """The image of the newest reading not returned before, waiting up to ``timeout_ms`` for one.

        Raises
        ------
        TimeoutError
            No new reading within ``timeout_ms``.
        """
        reading = self._sensor().latest(timeout_s=max(timeout_ms, 0.0) / 1000.0)
        if reading is None:
            raise TimeoutError(f"{self}: no new reading within {timeout_ms:g} ms")
        self.taken += 1
        return self._keep(reading)

    def read(self, color_mode: object = None) -> np.ndarray:
        """The next reading's image (waits for it, up to a second)."""
        return self.async_read(timeout_ms=1000)

    def read_latest(self, max_age_ms: int = 500) -> np.ndarray:
        """The newest image, without waiting (a reading already returned may be returned again).

        Raises
        ------
        TimeoutError
            The newest reading is older than ``max_age_ms``.
        RuntimeError
            No reading yet.
        """
        reading = self._sensor().latest()
        if reading is not None:
            self._keep(reading)
        if self._last is None:
            raise RuntimeError(f"{self}: no reading yet")
        image, t_ns = self._last
        age_ms = (time.monotonic_ns() - t_ns) / 1e6
        if age_ms > max_age_ms:
            raise TimeoutError(f"{self}: the newest reading is {age_ms:.1f} ms old (max {max_age_ms} ms)")
        return image

    def status(self) -> ot.Status:
        """The sensor's counters (frames read, unread, dropped by its camera)."""
        return self._sensor().status()

    def disconnect(self) -> None:
        """Stop the background reading and close the sensor."""
        sensor = self._sensor()
        self.sensor = None
        sensor.close()
