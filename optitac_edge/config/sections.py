"""The board config's sections: one frozen dataclass each, every field with its checker, default and doc.

The sections of the board itself are here; a device's is declared beside the device (``[camera]``,
``[link]``, ``[led]``, ``[rig]``, ``[network]`` and each ``[publish.NAME]``) and read through its registry.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from optitac_edge.errors import ConfigError
from optitac_edge.fields import CAMERA_NAME, boolean, choice, integer, number, path_text, region_box, setting, string
from optitac_edge.io.cameras import CameraConfig
from optitac_edge.io.led import LedConfig
from optitac_edge.io.publishers import PUBLISHERS, NetworkConfig
from optitac_edge.io.rigs import RigConfig
from optitac_edge.io.transports import LinkConfig

#: Where systemd's ``StateDirectory=optitac-edge`` lives (the calibration bundle's home).
DEFAULT_STATE_DIR = "/var/lib/optitac-edge"


#: Most rest frames calibrated from at start (each is held in memory: 300 RGB 640x480 frames are 276 MB).
MAX_REST_FRAMES = 300


#: The name of the ``[camera]`` of a board written in the one-sensor form.
MAIN_CAMERA = "main"


# --------------------------------------------------------------------------- sections
# Each section is a frozen dataclass; each field's metadata holds its checker and a one-line doc.
# Defaults are what an empty file gives (the simulated sensor, no link, no LED).


@dataclass(frozen=True)
class SensorConfig:
    id: int = setting(integer(0, 255), 0, "sensor number sent to the MCU in every message")
    name: str = setting(string(64, pattern=r"[A-Za-z0-9_.-]+", empty=False), "optitac",
                        "short name for logs (letters, digits, _ . -)")
    camera: str = setting(string(32, pattern=CAMERA_NAME, empty=False), MAIN_CAMERA,
                          "the camera that reads this sensor's fibers: a [cameras.NAME] of the board "
                          "('main' is the [camera] of a one-camera board)")
    region: tuple[int, ...] = setting(region_box, (), "x, y, width, height of the camera frame holding this sensor's "
                                      "fibers, px ([] = the whole frame; several sensors on one camera each need one)")


@dataclass(frozen=True)
class CalibrationConfig:
    bundle: str = setting(path_text, f"{DEFAULT_STATE_DIR}/calibration.npz",
                          "calibration bundle ('' = calibrate at every start, keep nothing)")
    if_missing: str = setting(choice("calibrate", "fail"), "calibrate",
                              "no bundle: calibrate fibers from rest frames and save, or fail")
    if_mismatched: str = setting(choice("refuse", "remap"), "refuse",
                                 "a bundle the camera's rest frames do not fit (another skin, a moved camera): "
                                 "refuse it (no contact; STATUS says the sensor cannot tell), or map the fibers "
                                 "again from the rest frames at start, keeping the old bundle beside the new")
    rest_frames: int = setting(integer(1, MAX_REST_FRAMES), 10, "contact-free frames used to calibrate at start")
    rotation_deg: float = setting(number(-360, 360), 0.0, "orientation hint (docs/formats.md)")
    mirror: bool = setting(boolean, False, "orientation hint: the array appears mirrored")
    layout: str = setting(path_text, "", "custom layout CSV ('' = the default hexagonal array)")

    @property
    def bundle_path(self) -> Path | None:
        return Path(self.bundle) if self.bundle else None

    @property
    def layout_path(self) -> Path | None:
        return Path(self.layout) if self.layout else None


@dataclass(frozen=True)
class StatusConfig:
    period_s: float = setting(number(0.05, 3600), 1.0, "period of STATUS messages and log lines, s")


@dataclass(frozen=True)
class WatchdogConfig:
    enabled: bool = setting(boolean, True, "kick systemd's watchdog from the frame loop (if WatchdogSec set)")
    max_frame_gap_s: float = setting(number(0.1, 600), 2.0, "no frame for this long: stop kicking, exit with failure")


_SECTIONS: dict[str, type] = {
    "sensor": SensorConfig,
    "camera": CameraConfig,
    "calibration": CalibrationConfig,
    "link": LinkConfig,
    "led": LedConfig,
    "status": StatusConfig,
    "watchdog": WatchdogConfig,
    "rig": RigConfig,
    "network": NetworkConfig,
}


def publish_section(name: str, source: str) -> type:
    """The ``[publish.NAME]`` section of the publisher the registry names ``name`` (its module imported; its
    optional library is not).

    Raises
    ------
    ConfigError
        No publisher of that name (``source``: where it was asked for).
    """
    if name not in PUBLISHERS:
        raise ConfigError(f"{source}: publish.{name}: no such publisher (known: {', '.join(PUBLISHERS)})")
    with PUBLISHERS.importing(name):
        section: type = PUBLISHERS.load(name).Section
    return section


_TOP_LEVEL = {"config_version", "description"}


#: The tables of a board with several sensors: ``[cameras.NAME]`` and ``[[sensors]]``; the publishers
#: ``[publish.NAME]``.
_LISTS = ("cameras", "sensors", "publish")


#: ``[calibration]`` keys a ``[[sensors]]`` entry sets for its sensor (the rest are board-wide).
SENSOR_CALIBRATION_KEYS = ("bundle", "layout", "rotation_deg", "mirror")
