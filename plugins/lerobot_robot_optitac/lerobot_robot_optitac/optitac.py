"""An OptiTac sensor's contacts as a LeRobot robot's observations, alone or beside an arm.

The sensor is read through the OptiTac camera plugin (``lerobot_camera_optitac``: optitac-edge's public API, the
sensor's own background thread at its own rate, so velocity, slip and vibration come from every frame); at each
of LeRobot's frames the newest reading gives the tactile image and these observations (LeRobot gathers the
numbers into ``observation.state``, each named):

- ``optitac.contact<K>.<field>`` for each of the 4 contact slots, strongest first (the fields of optitac-edge's
  ``export-lerobot``: present, x_mm, y_mm, major_mm, minor_mm, angle_deg, depth_mm, force_n, vx_mm_s, vy_mm_s,
  sliding, contact_id; an empty slot all 0, an unknown value NaN);
- ``optitac.n_contacts``, ``optitac.vibration``, ``optitac.vibrating``, ``optitac.baseline_ready``,
  ``optitac.saturated``, ``optitac.frame`` (the sensor's frame number) and ``optitac.t_ns`` (its capture time,
  CLOCK_MONOTONIC ns, exact below 2**53 ns: 104 days of uptime);
- with ``fibers``, ``optitac.fiber<ID>``: each fiber's signal.
"""

from __future__ import annotations

import math
from functools import cached_property
from typing import Any

from lerobot.cameras.utils import make_cameras_from_configs
from lerobot.robots.robot import Robot
from lerobot.robots.utils import make_robot_from_config
from lerobot.utils.errors import DeviceNotConnectedError
from lerobot_camera_optitac import OptiTacCamera

import optitac_edge as ot
from lerobot_robot_optitac.config_optitac import OptiTacConfig
from optitac_edge.core.options import MAX_CONTACTS
from optitac_edge.devtools.lerobot_features import CONTACT_FIELDS, IMAGE_SIDE, STATE_FIELDS, contact_slot

PREFIX = "optitac"


def reading_values(reading: ot.Reading, fiber_ids: list[int] | None) -> dict[str, float]:
    """The observations of one reading (see the module's description), every value a float."""
    out: dict[str, float] = {}
    for k in range(MAX_CONTACTS):
        c = reading.contacts[k] if k < len(reading.contacts) else None
        values = (0.0,) * len(CONTACT_FIELDS) if c is None else contact_slot(c, c.id)
        out.update({f"{PREFIX}.contact{k}.{f}": v for f, v in zip(CONTACT_FIELDS, values)})
    state = (len(reading.contacts), reading.vibration, reading.vibrating, reading.baseline_ready, reading.saturated)
    out.update({f"{PREFIX}.{f}": float(v) for f, v in zip(STATE_FIELDS, state)})
    out[f"{PREFIX}.frame"] = float(reading.frame)
    out[f"{PREFIX}.t_ns"] = float(reading.t_ns)
    if fiber_ids is not None:
        fibers = reading.fibers if reading.fibers is not None else [math.nan] * len(fiber_ids)
        out.update({f"{PREFIX}.fiber{i}": float(v) for i, v in zip(fiber_ids, fibers)})
    return out


class OptiTac(Robot):
    """LeRobot's robot contract over one OptiTac sensor and, optionally, the arm it sits on."""

    config_class = OptiTacConfig
    name = "optitac"

    def __init__(self, config: OptiTacConfig) -> None:
        super().__init__(config)
        self.config = config
        self.arm: Robot | None = None if config.arm is None else make_robot_from_config(config.arm)
        self.tactile = OptiTacCamera(config.tactile)
        self.cameras = make_cameras_from_configs(config.cameras)

    @cached_property
    def _fiber_names(self) -> list[int] | None:
        if not self.config.fibers:
            return None
        from optitac_edge.config import load_board_config
        from optitac_edge.core.layout import hex_layout
        from optitac_edge.io.layout_csv import load_layout_csv

        layout_path = load_board_config(self.config.tactile.board).calibration.layout_path
        layout = load_layout_csv(layout_path) if layout_path else hex_layout()
        return [int(i) for i in layout.ids]

    @property
    def observation_features(self) -> dict[str, Any]:
        numbers = [f"{PREFIX}.contact{k}.{f}" for k in range(MAX_CONTACTS) for f in CONTACT_FIELDS]
        numbers += [f"{PREFIX}.{f}" for f in (*STATE_FIELDS, "frame", "t_ns")]
        numbers += [f"{PREFIX}.fiber{i}" for i in self._fiber_names or []]
        out: dict[str, Any] = {} if self.arm is None else dict(self.arm.observation_features)
        out.update(dict.fromkeys(numbers, float))
        if self.config.image:
            out[PREFIX] = (IMAGE_SIDE, IMAGE_SIDE, 3)
        for key, cam in self.config.cameras.items():
            out[key] = (cam.height, cam.width, 3)
        return out

    @property
    def action_features(self) -> dict[str, type]:
        return {} if self.arm is None else dict(self.arm.action_features)

    @property
    def is_connected(self) -> bool:
        arm = self.arm is None or self.arm.is_connected
        return arm and self.tactile.is_connected and all(c.is_connected for c in self.cameras.values())

    def connect(self, calibrate: bool = True) -> None:
        """The arm (if any), its cameras, then the sensor (waiting for its baseline)."""
        if self.arm is not None:
            self.arm.connect(calibrate)
        for cam in self.cameras.values():
            cam.connect()
        self.tactile.connect()

    @property
    def is_calibrated(self) -> bool:
        return self.arm is None or self.arm.is_calibrated

    def calibrate(self) -> None:
        """The arm's calibration (the sensor's is optitac-edge's bundle, made with its own commands)."""
        if self.arm is not None:
            self.arm.calibrate()

    def configure(self) -> None:
        if self.arm is not None:
            self.arm.configure()

    def get_observation(self) -> dict[str, Any]:
        """The arm's observation, the newest tactile reading's numbers and image, and the cameras' images."""
        if not self.tactile.is_connected:
            raise DeviceNotConnectedError(f"{self} is not connected.")
        out: dict[str, Any] = {} if self.arm is None else dict(self.arm.get_observation())
        image = self.tactile.async_read(timeout_ms=1000)
        reading = self.tactile.last_reading
        assert reading is not None
        out.update(reading_values(reading, self._fiber_names))
        if self.config.image:
            out[PREFIX] = image
        for key, cam in self.cameras.items():
            out[key] = cam.async_read()
        return out

    def send_action(self, action: dict[str, Any]) -> dict[str, Any]:
        """To the arm; without one, nothing to act on (the action is returned as sent)."""
        return action if self.arm is None else self.arm.send_action(action)

    def status(self) -> ot.Status:
        """The sensor's counters (frames read, unread, dropped by its camera)."""
        return self.tactile.status()

    def disconnect(self) -> None:
        """The sensor, the cameras and the arm."""
        self.tactile.disconnect()
        for cam in self.cameras.values():
            cam.disconnect()
        if self.arm is not None:
            self.arm.disconnect()
