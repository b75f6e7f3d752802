"""Board configuration: which camera, link, LED ring and calibration one board uses.

A board config is a TOML file (see ``board_configs/`` and docs/deploy.md). It is
read with :func:`load_board_config`, which layers three sources, later ones
winning:

1. the file (a path, or a NAME such as ``sim`` that resolves to the packaged
   ``board_configs/NAME.toml``);
2. environment variables ``OPTITAC_<SECTION>_<KEY>`` (e.g. ``OPTITAC_LINK_SERIAL_URL``,
   ``OPTITAC_CAMERA_OPTIONS_<NAME>`` for a camera option);
3. ``overrides`` from the command line, ``{"section.key": value}``.

Every value is validated strictly: an unknown section or key, a wrong type or an
out-of-range value raises :class:`~optitac_edge.errors.ConfigError` with one line
naming the source (file path, environment variable or "command line") and the key.
Nothing here touches hardware.
"""

from __future__ import annotations

import logging
import math
import os
import re
import sys
from collections.abc import Callable, Mapping
from dataclasses import MISSING, dataclass, field, fields, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10 (JetPack 6 / Ubuntu 22.04)
    import tomli as tomllib

from optitac_edge.errors import ConfigError
from optitac_edge.io.cameras import MAX_QUEUE_FRAMES
from optitac_edge.io.transports import TRANSPORTS
from optitac_edge.text import parse_float, parse_int

log = logging.getLogger(__name__)

#: Where systemd's ``StateDirectory=optitac-edge`` lives (the calibration bundle's home).
DEFAULT_STATE_DIR = "/var/lib/optitac-edge"
#: Prefix of the environment variables that override file values.
ENV_PREFIX = "OPTITAC_"
#: Most rest frames calibrated from at start (each is held in memory: 300 RGB 640x480 frames are 276 MB).
MAX_REST_FRAMES = 300
#: The only schema version there is.
CONFIG_VERSION = 1

Scalar = str | int | float | bool


class _Bad(Exception):
    """A value failed validation; the message says why (no source/key yet)."""


# --------------------------------------------------------------------------- value checkers
# A checker takes (value, from_text) and returns the converted value or raises _Bad.
# ``from_text`` is True for environment variables and string command-line overrides.

Checker = Callable[[Any, bool], Any]


def _show(value: Any) -> str:
    return repr(value) if isinstance(value, str) else f"{value!r} ({_type_name(value)})"


def _type_name(value: Any) -> str:
    return {bool: "boolean", int: "integer", float: "float", str: "string", list: "array",
            dict: "table"}.get(type(value), type(value).__name__)


def _int(lo: int, hi: int, what: str = "an integer") -> Checker:
    def check(value: Any, from_text: bool) -> int:
        if from_text and isinstance(value, str):
            try:
                value = parse_int(value)
            except ValueError:
                raise _Bad(f"must be {what} in {lo}..{hi} (ASCII digits), got {value!r}") from None
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise _Bad(f"must be {what} in {lo}..{hi}, got {_show(value)}")
        return value
    return check


def _num(lo: float, hi: float, *, lo_open: bool = False) -> Checker:
    rng = f"{lo:g} < x <= {hi:g}" if lo_open else f"{lo:g}..{hi:g}"

    def check(value: Any, from_text: bool) -> float:
        if from_text and isinstance(value, str):
            try:
                value = parse_float(value)
            except ValueError:
                raise _Bad(f"must be a number in {rng} (ASCII digits), got {value!r}") from None
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        if ok:
            ok = (lo < value if lo_open else lo <= value) and value <= hi
        if not ok:
            raise _Bad(f"must be a number in {rng}, got {_show(value)}")
        return float(value)
    return check


_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


def _bool(value: Any, from_text: bool) -> bool:
    if from_text and isinstance(value, str):
        text = value.strip().lower()
        if text in _TRUE:
            return True
        if text in _FALSE:
            return False
        raise _Bad(f"must be true or false, got {value!r}")
    if not isinstance(value, bool):
        raise _Bad(f"must be true or false, got {_show(value)}")
    return value


def _str(max_len: int = 1024, *, pattern: str | None = None, empty: bool = True) -> Checker:
    def check(value: Any, from_text: bool) -> str:
        if not isinstance(value, str):
            raise _Bad(f"must be a string, got {_show(value)}")
        if not empty and not value:
            raise _Bad("must not be empty")
        if len(value) > max_len:
            raise _Bad(f"must be at most {max_len} characters, got {len(value)}")
        if "\x00" in value:
            raise _Bad("must not contain NUL")
        if pattern is not None and value and not re.fullmatch(pattern, value):
            raise _Bad(f"must match {pattern}, got {value!r}")
        return value
    return check


def _choice(*choices: str) -> Checker:
    def check(value: Any, from_text: bool) -> str:
        if not isinstance(value, str) or value not in choices:
            raise _Bad(f"must be one of {', '.join(repr(c) for c in choices)}, got {_show(value)}")
        return value
    return check


def _camera_backend(value: Any, from_text: bool) -> str:
    from optitac_edge.io.cameras import BACKENDS

    return _choice(*sorted(BACKENDS))(value, from_text)  # the registry is the one list of names


def _path(value: Any, from_text: bool) -> str:
    # Kept as text here; resolved against the file's directory by the loader. "" means "none".
    return _str(4096)(value, from_text)


def _int_list(value: Any, from_text: bool, what: str) -> Any:
    """Text ``'0,1,2'`` (environment, command line) as a list of integers, a tuple as a list; else ``value``."""
    if from_text and isinstance(value, str):
        try:
            return [parse_int(part) for part in value.split(",") if part.strip()]
        except ValueError:
            raise _Bad(f"must be {what}, got {value!r}") from None
    return list(value) if isinstance(value, tuple) else value


def _channels(value: Any, from_text: bool) -> tuple[int, ...]:
    value = _int_list(value, from_text, "a list of channel numbers 0..15 (e.g. '0,1,2')")
    if isinstance(value, (bool, int)):
        value = [value]
    if not isinstance(value, list) or not value:
        raise _Bad(f"must be a non-empty array of channel numbers 0..15, got {_show(value)}")
    for item in value:
        if isinstance(item, bool) or not isinstance(item, int) or not 0 <= item <= 15:
            raise _Bad(f"channels must be integers in 0..15, got {_show(item)}")
    if len(set(value)) != len(value):
        raise _Bad(f"channels must be unique, got {value!r}")
    return tuple(value)


#: How a camera of a board is named: ``[cameras.NAME]``; a one-camera board's ``[camera]`` is "main".
CAMERA_NAME = r"[A-Za-z][A-Za-z0-9_-]{0,31}"
#: The name of the ``[camera]`` of a board written in the one-sensor form.
MAIN_CAMERA = "main"


def _region(value: Any, from_text: bool) -> tuple[int, ...]:
    value = _int_list(value, from_text, "x, y, width, height in px (e.g. '0,20,440,360')")
    if not isinstance(value, list) or len(value) not in (0, 4):
        raise _Bad(f"must be [x, y, width, height] in px, or [] for the whole frame, got {_show(value)}")
    if any(isinstance(v, bool) or not isinstance(v, int) for v in value):
        raise _Bad(f"must be 4 integers [x, y, width, height], got {value!r}")
    if value and (value[0] < 0 or value[1] < 0 or value[2] < 16 or value[3] < 16):
        raise _Bad(f"needs x, y >= 0 and a width and height of at least 16 px, got {value!r}")
    return tuple(value)


def _scalar(value: Any, from_text: bool) -> Scalar:
    if from_text and isinstance(value, str):
        try:  # a TOML literal (number, boolean, quoted string), else the text itself
            text = value
            value = tomllib.loads(f"v = {value}")["v"]
        except tomllib.TOMLDecodeError:
            return value
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            try:  # TOML takes 30_0 as 300: a number from the environment is written plainly
                value = parse_int(text) if isinstance(value, int) else parse_float(text)
            except ValueError:
                raise _Bad(f"a number must be written with ASCII digits and no '_', got {text!r}") from None
    if not isinstance(value, (str, int, float, bool)):
        raise _Bad(f"must be a scalar (string, number or boolean), got {_type_name(value)}")
    if isinstance(value, float) and not math.isfinite(value):
        raise _Bad(f"must be finite, got {value!r}")
    return value


def _opt(check: Checker, default: Any, doc: str) -> Any:
    return field(default=default, metadata={"check": check, "doc": doc})


# --------------------------------------------------------------------------- sections
# Each section is a frozen dataclass; each field's metadata holds its checker and a one-line doc.
# Defaults are what an empty file gives (the simulated sensor, no link, no LED).


@dataclass(frozen=True)
class SensorConfig:
    id: int = _opt(_int(0, 255), 0, "sensor number sent to the MCU in every message")
    name: str = _opt(_str(64, pattern=r"[A-Za-z0-9_.-]+", empty=False), "optitac",
                     "short name for logs (letters, digits, _ . -)")
    camera: str = _opt(_str(32, pattern=CAMERA_NAME, empty=False), MAIN_CAMERA,
                       "the camera that reads this sensor's fibers: a [cameras.NAME] of the board "
                       "('main' is the [camera] of a one-camera board)")
    region: tuple[int, ...] = _opt(_region, (), "x, y, width, height of the camera frame holding this sensor's "
                                   "fibers, px ([] = the whole frame; several sensors on one camera each need one)")


@dataclass(frozen=True)
class CameraConfig:
    backend: str = _opt(_camera_backend, "sim", "camera backend: sim, recording, picamera2, v4l2")
    width: int = _opt(_int(16, 8192), 640, "image width, px")
    height: int = _opt(_int(16, 8192), 480, "image height, px")
    fps: float = _opt(_num(1, 1000), 60.0, "frame rate, frames/s")
    pixel_format: str = _opt(_choice("gray", "rgb", "yuv420"), "gray", "pixel format delivered")
    exposure_us: int = _opt(_int(0, 10_000_000), 0, "exposure time, µs (0 = automatic)")
    gain: float = _opt(_num(0, 64), 0.0, "analogue gain (0 = automatic)")
    index: int = _opt(_int(0, 15), 0, "picamera2: camera number")
    device: str = _opt(_path, "", "v4l2: device node, best a /dev/v4l/by-id/... path")
    pipeline: str = _opt(_str(4096), "", "v4l2: a GStreamer pipeline ending in appsink (instead of device)")
    recording: str = _opt(_path, "", "recording: the recording directory to replay")
    warmup_frames: int = _opt(_int(0, 1000), 5, "frames discarded after opening (auto exposure settles)")
    timeout_s: float = _opt(_num(0, 60, lo_open=True), 1.0, "longest wait for one frame, s")
    queue_frames: int = _opt(_int(1, MAX_QUEUE_FRAMES), 4, "frames that may wait for the loop; when full the oldest "
                             "is dropped (1 = latest frame only)")
    #: Backend-specific options (free names, scalar values), validated by the backend.
    options: Mapping[str, Scalar] = field(default_factory=lambda: MappingProxyType({}),
                                          metadata={"doc": "backend-specific options (scalars)"})


@dataclass(frozen=True)
class CalibrationConfig:
    bundle: str = _opt(_path, f"{DEFAULT_STATE_DIR}/calibration.npz",
                       "calibration bundle ('' = calibrate at every start, keep nothing)")
    if_missing: str = _opt(_choice("calibrate", "fail"), "calibrate",
                           "no bundle: calibrate fibers from rest frames and save, or fail")
    rest_frames: int = _opt(_int(1, MAX_REST_FRAMES), 10, "contact-free frames used to calibrate at start")
    rotation_deg: float = _opt(_num(-360, 360), 0.0, "orientation hint (docs/formats.md)")
    mirror: bool = _opt(_bool, False, "orientation hint: the array appears mirrored")
    layout: str = _opt(_path, "", "custom layout CSV ('' = the default hexagonal array)")

    @property
    def bundle_path(self) -> Path | None:
        return Path(self.bundle) if self.bundle else None

    @property
    def layout_path(self) -> Path | None:
        return Path(self.layout) if self.layout else None


@dataclass(frozen=True)
class LinkConfig:
    transport: str = _opt(_choice(*TRANSPORTS), "none", "link to the MCU: " + ", ".join(TRANSPORTS))
    serial_url: str = _opt(_str(4096), "", "serial: pyserial URL or device, e.g. /dev/optitac-mcu")
    baudrate: int = _opt(_int(1200, 12_000_000), 115_200, "serial: baud rate (ignored by USB CDC)")
    can_channel: str = _opt(_str(64), "can0", "can: python-can channel (socketcan: interface name)")
    can_interface: str = _opt(_str(64, pattern=r"[a-z0-9_]+", empty=False), "socketcan",
                              "can: python-can interface")
    can_bitrate: int = _opt(_int(10_000, 1_000_000), 500_000,
                            "can: bit rate (socketcan: set on the interface, docs/deploy.md)")
    can_protocol: int = _opt(_int(1, 2), 1,
                             "can: 2 adds protocol v2's CONTACT2 and RELEASE frames (every contact with depth, "
                             "force and id) on their own ids beside the v1 frames (docs/can.md)")
    rate_divider: int = _opt(_int(1, 1000), 1, "send the contact of every Nth frame")

@dataclass(frozen=True)
class LedConfig:
    enabled: bool = _opt(_bool, False, "drive an LED ring through an I2C PWM chip")
    driver: str = _opt(_choice("pca9685"), "pca9685", "LED driver chip")
    i2c_bus: int = _opt(_int(0, 255), 1, "I2C bus number (/dev/i2c-N)")
    address: int = _opt(_int(0x03, 0x77, "a 7-bit I2C address"), 0x40, "I2C address of the chip")
    channels: tuple[int, ...] = _opt(_channels, (0,), "PWM channels the LEDs are on")
    brightness: float = _opt(_num(0, 1), 0.5, "LED brightness, 0..1 (duty cycle)")
    pwm_frequency_hz: int = _opt(_int(24, 1526), 1000, "PWM frequency, Hz")
    invert: bool = _opt(_bool, False, "invert outputs (LEDs wired to V+ without a driver)")
    open_drain: bool = _opt(_bool, False, "open-drain outputs instead of totem pole")
    adjust_at_calibration: bool = _opt(_bool, True, "lower brightness at calibration until no fiber saturates")
    max_peak: int = _opt(_int(1, 255), 230, "highest allowed fiber peak, gray level")
    peak_percentile: float = _opt(_num(50, 100), 99.9, "percentile of fiber pixels taken as the peak")


@dataclass(frozen=True)
class StatusConfig:
    period_s: float = _opt(_num(0.05, 3600), 1.0, "period of STATUS messages and log lines, s")


@dataclass(frozen=True)
class WatchdogConfig:
    enabled: bool = _opt(_bool, True, "kick systemd's watchdog from the frame loop (if WatchdogSec set)")
    max_frame_gap_s: float = _opt(_num(0.1, 600), 2.0, "no frame for this long: stop kicking, exit with failure")


@dataclass(frozen=True)
class RigConfig:
    """The indentation rig of ``optitac-edge collect`` (bench use only; the service never moves it)."""

    url: str = _opt(_str(256), "", "gcode://PORT (GRBL), ur://HOST (Universal Robots) or sim:// (simulator)")
    baudrate: int = _opt(_int(1200, 4_000_000), 115200, "gcode: serial baud rate")
    home: bool = _opt(_bool, False, "gcode: home ($H) at start when the machine is locked")
    x_min: float = _opt(_num(-1e5, 1e5), 0.0, "lowest x the tip may go to, mm (rig coordinates)")
    x_max: float = _opt(_num(-1e5, 1e5), 0.0, "highest x, mm")
    y_min: float = _opt(_num(-1e5, 1e5), 0.0, "lowest y, mm")
    y_max: float = _opt(_num(-1e5, 1e5), 0.0, "highest y, mm")
    z_min: float = _opt(_num(-1e5, 1e5), 0.0, "lowest z (deepest), mm: keep it above what the skin can take")
    z_max: float = _opt(_num(-1e5, 1e5), 0.0, "highest z, mm")
    safe_z: float = _opt(_num(-1e5, 1e5), 0.0, "z of every retract, mm (0: z_max)")
    feed_mm_s: float = _opt(_num(0.1, 500), 10.0, "speed of every move, mm/s")

    @property
    def limits_set(self) -> bool:
        return self.x_min < self.x_max and self.y_min < self.y_max and self.z_min < self.z_max


def _endpoints(value: Any, from_text: bool) -> tuple[str, ...]:
    if from_text and isinstance(value, str):
        value = [part.strip() for part in value.split(",") if part.strip()]
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
        raise _Bad(f"must be a list of Zenoh endpoints such as 'tcp/192.168.1.10:7447', got {_show(value)}")
    for v in value:
        if not re.fullmatch(r"[a-z][a-z0-9-]*/\S+", v):
            raise _Bad(f"{v!r} is not a Zenoh endpoint (PROTOCOL/ADDRESS, e.g. 'tcp/192.168.1.10:7447')")
    return tuple(value)


ROS_NAME = r"[A-Za-z](_?[A-Za-z0-9])*"


@dataclass(frozen=True)
class NetworkConfig:
    """What every publisher of the board shares (``[network]``; docs/network.md)."""

    namespace: str = _opt(_str(200, pattern=f"(/{ROS_NAME})*"), "",
                          "ROS 2 namespace of the topics, e.g. '/robot1' ('' = none: /optitac/SENSOR/...)")
    signal_hz: float = _opt(_num(0, 1000), 0.0, "per-fiber signal messages per second and sensor (0: none)")
    picture_hz: float = _opt(_num(0, 120), 0.0,
                             "each sensor's camera image, surface and overlay per second (0: none; 10 with foxglove "
                             "when left at 0)")
    queue: int = _opt(_int(8, 1_000_000), 256,
                      "messages held for the publishing thread before the oldest is dropped (and counted)")


@dataclass(frozen=True)
class ZenohPublish:
    """``[publish.zenoh]``: every sensor's contacts, status and signal as ROS 2 topics via rmw_zenoh."""

    config: str = _opt(_path, "", "a Zenoh JSON5 config file (endpoints, scouting, TLS); '' = Zenoh's defaults")
    mode: str = _opt(_choice("", "peer", "client", "router"), "", "session mode ('' = the config file's, else peer)")
    connect: tuple[str, ...] = _opt(_endpoints, (), "endpoints to connect to, e.g. ['tcp/192.168.1.10:7447']")
    listen: tuple[str, ...] = _opt(_endpoints, (), "endpoints to listen on, e.g. ['tcp/0.0.0.0:7447']")
    domain_id: int = _opt(_int(0, 232), 0, "ROS 2 domain id (ROS_DOMAIN_ID)")
    node: str = _opt(_str(64, pattern=ROS_NAME, empty=False), "optitac_edge", "ROS 2 node name")

    def kwargs(self) -> dict[str, Any]:
        """The publisher's constructor arguments."""
        return {"config": Path(self.config) if self.config else None, "mode": self.mode, "connect": self.connect,
                "listen": self.listen, "domain_id": self.domain_id, "node": self.node}


@dataclass(frozen=True)
class FoxglovePublish:
    """``[publish.foxglove]``: everything live to Foxglove / Lichtblick (a WebSocket server)."""

    bind: str = _opt(_str(256, pattern=r"\S+:\d{1,5}", empty=False), "127.0.0.1:8765", "serve on HOST:PORT")

    def kwargs(self) -> dict[str, Any]:
        return {"bind": self.bind}


@dataclass(frozen=True)
class McapPublish:
    """``[publish.mcap]``: a recording of what is published, in MCAP files."""

    path: str = _opt(_path, "", "the MCAP file (required)")
    max_mb: float = _opt(_num(0, 1e7), 0.0, "start a new file (NAME-0001.mcap, ...) after this many MB of messages (0: never)")
    max_minutes: float = _opt(_num(0, 1e6), 0.0, "start a new file after this many minutes (0: never)")
    keep_mb: float = _opt(_num(0, 1e9), 0.0, "delete the recording's oldest complete files once they hold more than "
                          "this many MB (0: keep all)")

    def kwargs(self) -> dict[str, Any]:
        return {"path": Path(self.path), "max_bytes": int(self.max_mb * 1e6), "max_ns": int(self.max_minutes * 60e9),
                "keep_bytes": int(self.keep_mb * 1e6)}


@dataclass(frozen=True)
class VirtualPublish:
    """``[publish.virtual]``: kept in memory (tests)."""

    def kwargs(self) -> dict[str, Any]:
        return {}


#: Each publisher of the registry (:data:`optitac_edge.io.publishers.PUBLISHERS`) and its ``[publish.NAME]`` section.
PUBLISH_SECTIONS: dict[str, type] = {"zenoh": ZenohPublish, "foxglove": FoxglovePublish, "mcap": McapPublish,
                                     "virtual": VirtualPublish}
PublishSection = ZenohPublish | FoxglovePublish | McapPublish | VirtualPublish


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
#: Keys holding paths, resolved against the directory of the file that set them.
_PATH_KEYS = {("camera", "device"), ("camera", "recording"), ("calibration", "bundle"),
              ("calibration", "layout"), ("publish.zenoh", "config"), ("publish.mcap", "path")}
_TOP_LEVEL = {"config_version", "description"}
#: The tables of a board with several sensors: ``[cameras.NAME]`` and ``[[sensors]]``; the publishers
#: ``[publish.NAME]``.
_LISTS = ("cameras", "sensors", "publish")
#: ``[calibration]`` keys a ``[[sensors]]`` entry sets for its sensor (the rest are board-wide).
SENSOR_CALIBRATION_KEYS = ("bundle", "layout", "rotation_deg", "mirror")


@dataclass(frozen=True)
class BoardSensor:
    """One sensor of a board: its id, name, camera and region (``sensor``) and its calibration."""

    sensor: SensorConfig
    calibration: CalibrationConfig

    @property
    def label(self) -> str:
        """How errors and logs name it: ``sensor 2 'palm'``."""
        return f"sensor {self.sensor.id} {self.sensor.name!r}"


@dataclass(frozen=True)
class BoardConfig:
    """A validated board configuration (all sections, defaults filled in).

    A board written in the one-sensor form (``[sensor]``, ``[camera]``,
    ``[calibration]``) has one sensor on the camera named ``main``. A board with
    ``[cameras.NAME]`` tables and ``[[sensors]]`` entries lists them in
    :attr:`sensors` and :attr:`cameras`; its ``sensor``, ``camera`` and
    ``calibration`` are then its first sensor's, and :meth:`for_sensor` narrows
    the board to any one of them (what ``--sensor ID`` does).
    """

    source: str = "(defaults)"
    description: str = ""
    sensor: SensorConfig = field(default_factory=SensorConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    link: LinkConfig = field(default_factory=LinkConfig)
    led: LedConfig = field(default_factory=LedConfig)
    status: StatusConfig = field(default_factory=StatusConfig)
    watchdog: WatchdogConfig = field(default_factory=WatchdogConfig)
    rig: RigConfig = field(default_factory=RigConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    #: The publishers (``[publish.NAME]``), by registry name, in file order.
    publish: Mapping[str, PublishSection] = field(default_factory=lambda: MappingProxyType({}))
    #: "section.key" -> where its value came from (file path, "OPTITAC_..." or "command line").
    origins: Mapping[str, str] = field(default_factory=lambda: MappingProxyType({}), compare=False)
    #: The ``[[sensors]]`` of a board with several (empty in the one-sensor form).
    listed_sensors: tuple[BoardSensor, ...] = ()
    #: The ``[cameras.NAME]`` of a board with several sensors (empty when it has one ``[camera]``).
    named_cameras: Mapping[str, CameraConfig] = field(default_factory=lambda: MappingProxyType({}))
    #: The sensor :meth:`for_sensor` narrowed the board to (None: all of them).
    selected: int | None = None

    @property
    def all_sensors(self) -> tuple[BoardSensor, ...]:
        """Every sensor of the board in file order, also when narrowed to one."""
        return self.listed_sensors or (BoardSensor(self.sensor, self.calibration),)

    @property
    def sensors(self) -> tuple[BoardSensor, ...]:
        """The sensors this config runs: all of the board's, or the one it was narrowed to."""
        return tuple(s for s in self.all_sensors if self.selected is None or s.sensor.id == self.selected)

    @property
    def cameras(self) -> Mapping[str, CameraConfig]:
        """The cameras the :attr:`sensors` are read by, by name (``main`` for a board with one ``[camera]``)."""
        if not self.named_cameras:
            return MappingProxyType({MAIN_CAMERA: self.camera})
        used = {s.sensor.camera for s in self.sensors}
        return MappingProxyType({k: v for k, v in self.named_cameras.items() if k in used})

    def sensors_of(self, camera: str) -> tuple[BoardSensor, ...]:
        """The sensors of :attr:`sensors` that ``camera`` reads, in file order."""
        return tuple(s for s in self.sensors if s.sensor.camera == camera)

    def regions_of(self, camera: str) -> tuple[tuple[int, ...], ...]:
        """The regions of every sensor of the board on ``camera`` (also when narrowed to one), file order."""
        return tuple(s.sensor.region for s in self.all_sensors if s.sensor.camera == camera)

    def for_sensor(self, sensor_id: int | None = None) -> BoardConfig:
        """This board narrowed to one sensor: its ``sensor``, ``camera`` and ``calibration`` are that sensor's.

        ``None`` is the board's only sensor.

        Raises
        ------
        ConfigError
            No such sensor, or ``None`` on a board with several.
        """
        sensors = self.sensors
        ids = ", ".join(str(s.sensor.id) for s in sensors)
        if sensor_id is None:
            if len(sensors) == 1:
                return self
            raise ConfigError(f"{self.source}: the board has {len(sensors)} sensors (ids {ids}): "
                              "choose one with --sensor ID")
        for s in sensors:
            if s.sensor.id == sensor_id:
                if not self.listed_sensors:
                    return self
                return replace(self, sensor=s.sensor, camera=self.named_cameras.get(s.sensor.camera, self.camera),
                               calibration=s.calibration, selected=sensor_id)
        raise ConfigError(f"{self.source}: no sensor with id {sensor_id} (the board's: {ids})")

    def as_dict(self) -> dict[str, Any]:
        """Plain ``{section: {key: value}}`` (for ``--print-config`` and logs); a board with several
        sensors adds ``cameras`` ({name: {key: value}}) and ``sensors`` (a list of {key: value})."""
        out: dict[str, Any] = {}
        for name in _SECTIONS:
            out[name] = _plain(getattr(self, name))
        out["publish"] = {name: _plain(section) for name, section in self.publish.items()}
        if self.listed_sensors:
            out["cameras"] = {name: _plain(cam) for name, cam in self.named_cameras.items()}
            out["sensors"] = [{**_plain(s.sensor), **{k: v for k, v in _plain(s.calibration).items()
                                                       if k in SENSOR_CALIBRATION_KEYS}}
                              for s in self.listed_sensors]
        return out


def _plain(section: Any) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for f in fields(section):
        value = getattr(section, f.name)
        if isinstance(value, Mapping):
            value = dict(value)
        elif isinstance(value, tuple):
            value = list(value)
        out[f.name] = value
    return out


# --------------------------------------------------------------------------- loading


def packaged_config_dirs() -> list[Path]:
    """Directories searched for a board NAME, in order.

    The checkout's ``board_configs/`` (next to the package), then the installed
    copy (``<prefix>/share/optitac-edge/board_configs``, from the wheel's data files).
    """
    checkout = Path(__file__).resolve().parents[2]  # optitac_edge/service/board_config.py
    dirs = [checkout / "board_configs"]
    for prefix in dict.fromkeys((sys.prefix, sys.base_prefix, "/usr/local", "/usr")):
        dirs.append(Path(prefix) / "share" / "optitac-edge" / "board_configs")
    return dirs


def available_boards() -> list[str]:
    """Names of the packaged board configs."""
    names: set[str] = set()
    for d in packaged_config_dirs():
        if d.is_dir():
            names.update(p.stem for p in d.glob("*.toml"))
    return sorted(names)


def resolve_board_config(name_or_path: str | os.PathLike[str]) -> Path:
    """The file a board NAME (``sim``) or a path (anything with a ``/`` or ``.toml``) stands for."""
    text = os.fspath(name_or_path)
    if not text:
        raise ConfigError("board config: empty name")
    if "/" in text or text.endswith(".toml") or os.sep in text:
        path = Path(text)
        if not path.is_file():
            raise ConfigError(f"{text}: board config not found")
        return path
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", text):
        raise ConfigError(f"{text!r}: not a board name (known: {', '.join(available_boards())})")
    for d in packaged_config_dirs():
        candidate = d / f"{text}.toml"
        if candidate.is_file():
            return candidate
    raise ConfigError(f"{text}: no such board (known: {', '.join(available_boards()) or 'none'})")


def _display(path: Path) -> str:
    """``path`` relative to the working directory when it is below it (and that is not ``/``)."""
    cwd = Path.cwd().resolve()
    try:
        rel = path.resolve().relative_to(cwd)
    except ValueError:
        return str(path)
    return str(path) if cwd == Path(cwd.anchor) else str(rel)


def _read_toml(path: Path) -> dict[str, Any]:
    shown = _display(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except RecursionError:
        raise ConfigError(f"{shown}: not a board config (arrays or tables nested too deeply)") from None
    except FileNotFoundError:
        raise ConfigError(f"{shown}: board config not found") from None
    except OSError as exc:
        raise ConfigError(f"{shown}: cannot read board config ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{shown}: not UTF-8 text") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{shown}: not valid TOML ({str(exc).splitlines()[0]})") from None


class _Layers:
    """Values of every section/key with their source, applied in precedence order.

    Sections are stored by target: ``camera`` for the one-sensor form's
    ``[camera]``, ``cameras.NAME`` for a named camera (checked as a ``[camera]``).
    """

    def __init__(self) -> None:
        self.values: dict[str, dict[str, Any]] = {name: {} for name in _SECTIONS}
        self.options: dict[str, dict[str, Scalar]] = {"camera": {}}
        self.origins: dict[str, str] = {}
        #: The publishers turned on (``[publish.NAME]``), in the order they were.
        self.publishers: dict[str, str] = {}  # name -> the source that turned it on

    def add_camera(self, name: str) -> str:
        target = f"cameras.{name}"
        self.values.setdefault(target, {})
        self.options.setdefault(target, {})
        return target

    def publisher(self, source: str, name: str, on: bool = True) -> str:
        """Turn the publisher ``name`` on (with its defaults) or off; its section's target."""
        if name not in PUBLISH_SECTIONS:
            raise ConfigError(f"{source}: publish.{name}: no such publisher (known: {', '.join(PUBLISH_SECTIONS)})")
        target = f"publish.{name}"
        if on:
            self.publishers.setdefault(name, source)
            self.values.setdefault(target, {})
        else:
            self.publishers.pop(name, None)
            self.values.pop(target, None)
        return target

    def set(self, source: str, section: str, key: str, value: Any, *, from_text: bool,
            base_dir: Path | None, target: str | None = None) -> None:
        if section == "publish":
            name, _, key = key.partition(".")
            target = self.publisher(source, name)
            if not key:
                raise ConfigError(f"{source}: publish.{name}: set its keys as publish.{name}.KEY")
            cls = PUBLISH_SECTIONS[name]
            spec = {f.name: f for f in fields(cls)}
            if key not in spec:
                raise ConfigError(f"{source}: {target}.{key}: unknown key (known: {', '.join(spec) or 'none'})")
            self.values[target][key] = _check(spec[key], target, key, value, from_text, base_dir,
                                              f"{source}: {target}.{key}")
            self.origins[f"{target}.{key}"] = source
            return
        target = section if target is None else target
        where = f"{target}.{key}"
        if section not in _SECTIONS:
            raise ConfigError(f"{source}: {section}: unknown section (known: {', '.join((*_SECTIONS, *_LISTS))})")
        cls = _SECTIONS[section]
        spec = {f.name: f for f in fields(cls)}
        if section == "camera" and key.startswith("options."):
            name = key[len("options."):]
            if not re.fullmatch(r"[a-z][a-z0-9_]*", name):
                raise ConfigError(f"{source}: {where}: option names are lower-case identifiers")
            try:
                self.options[target][name] = _scalar(value, from_text)
            except _Bad as exc:
                raise ConfigError(f"{source}: {where}: {exc}") from None
            self.origins[where] = source
            return
        if key not in spec:
            close = [k for k in spec if k.replace("_", "") == key.replace("_", "").lower()]
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise ConfigError(f"{source}: {where}: unknown key{hint} (known: {', '.join(spec)})")
        if key == "options":  # a whole table from a file
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: {where}: must be a table, got {_type_name(value)}")
            for name, item in value.items():
                self.set(source, section, f"options.{name}", item, from_text=from_text, base_dir=base_dir,
                         target=target)
            return
        self.values[target][key] = _check(spec[key], section, key, value, from_text, base_dir,
                                          f"{source}: {where}")
        self.origins[where] = source

    def camera(self, target: str) -> CameraConfig:
        return CameraConfig(**{**self.values[target], "options": MappingProxyType(dict(self.options[target]))})

    def publish(self) -> Mapping[str, PublishSection]:
        return MappingProxyType({name: PUBLISH_SECTIONS[name](**self.values[f"publish.{name}"])
                                 for name in self.publishers})


def _check(spec: Any, section: str, key: str, value: Any, from_text: bool, base_dir: Path | None,
           where: str) -> Any:
    """``value`` checked by ``spec``'s checker (paths resolved against ``base_dir``); errors name ``where``."""
    try:
        converted = spec.metadata["check"](value, from_text)
    except _Bad as exc:
        raise ConfigError(f"{where}: {exc}") from None
    if (section, key) in _PATH_KEYS and converted and base_dir is not None:
        expanded = Path(os.path.expanduser(converted))
        converted = str(expanded if expanded.is_absolute() else base_dir / expanded)
    return converted


@dataclass
class _Entry:
    """One ``[[sensors]]`` entry as read: its sensor keys, its calibration keys, how errors name it."""

    sensor: dict[str, Any]
    calibration: dict[str, Any]
    label: str


def _apply_file(layers: _Layers, data: dict[str, Any], shown: str, base_dir: Path) -> tuple[str, list[_Entry]]:
    description = ""
    entries: list[_Entry] = []
    old: dict[str, Any] = {}
    for name, value in data.items():
        if name in _SECTIONS:
            if not isinstance(value, dict):
                raise ConfigError(f"{shown}: {name}: must be a table [{name}], got {_type_name(value)}")
            for key, item in value.items():
                layers.set(shown, name, key, item, from_text=False, base_dir=base_dir)
        elif name == "cameras":
            _apply_cameras(layers, value, shown, base_dir)
        elif name == "publish" and _new_publish(value):
            _apply_publish(layers, value, shown, base_dir)
        elif name in ("publish", "mcap"):
            old[name] = value
        elif name == "sensors":
            entries = _read_sensors(value, shown, base_dir)
        elif name == "config_version":
            if isinstance(value, bool) or value != CONFIG_VERSION:
                raise ConfigError(f"{shown}: config_version: must be {CONFIG_VERSION}, got {value!r}")
        elif name == "description":
            try:
                description = _str(400)(value, False)
            except _Bad as exc:
                raise ConfigError(f"{shown}: description: {exc}") from None
        else:
            kind = "section" if isinstance(value, dict) else "key"
            raise ConfigError(f"{shown}: {name}: unknown {kind} (known sections: "
                              f"{', '.join((*_SECTIONS, *_LISTS))})")
    if old:
        _apply_old_publish(layers, old, shown, base_dir)
    return description, entries


def _new_publish(value: Any) -> bool:
    """``[publish.NAME]`` tables (not the old form's ``[publish]`` keys)."""
    return isinstance(value, dict) and bool(value) and all(isinstance(v, dict) for v in value.values())


def _apply_publish(layers: _Layers, value: dict[str, Any], shown: str, base_dir: Path) -> None:
    for name, table in value.items():
        layers.publisher(shown, name)
        for key, item in table.items():
            layers.set(shown, "publish", f"{name}.{key}", item, from_text=False, base_dir=base_dir)


#: The old form's ``[publish]`` keys that are ``[network]``'s now.
_OLD_NETWORK_KEYS = ("namespace", "signal_hz", "picture_hz", "queue")


def _apply_old_publish(layers: _Layers, old: dict[str, Any], shown: str, base_dir: Path) -> None:
    """The old form (``[publish] backend``, ``foxglove``, the ``[mcap]`` section) read as ``[publish.NAME]`` and
    ``[network]``, with a one-line hint."""
    publish, mcap = old.get("publish", {}), old.get("mcap", {})
    for name, table in old.items():
        if not isinstance(table, dict):
            raise ConfigError(f"{shown}: {name}: must be a table [{name}], got {_type_name(table)}")
    became: list[str] = []
    publish = dict(publish)
    backend = publish.pop("backend", "none")
    if backend not in ("none", "zenoh", "virtual"):
        raise ConfigError(f"{shown}: publish.backend: must be one of none, zenoh, virtual, got {_show(backend)}")
    foxglove = publish.pop("foxglove", "")
    for key, item in publish.items():
        if key in _OLD_NETWORK_KEYS:
            layers.set(shown, "network", key, item, from_text=False, base_dir=base_dir)
            became.append(f"network.{key}")
        elif backend == "zenoh":
            layers.set(shown, "publish", f"zenoh.{key}", item, from_text=False, base_dir=base_dir)
            became.append(f"publish.zenoh.{key}")
        elif key not in {f.name for f in fields(ZenohPublish)}:
            raise ConfigError(f"{shown}: publish.{key}: unknown key")
    if backend != "none":
        layers.publisher(shown, backend)
        became.insert(0, f"[publish.{backend}]")
    if foxglove:
        layers.set(shown, "publish", "foxglove.bind", foxglove, from_text=False, base_dir=base_dir)
        became.append("publish.foxglove.bind")
    if mcap.get("path"):
        for key, item in mcap.items():
            layers.set(shown, "publish", f"mcap.{key}", item, from_text=False, base_dir=base_dir)
        became.append("[publish.mcap]")
    log.warning("%s: [publish] backend/foxglove and [mcap] are the old form, read as %s: write those "
                "(docs/network.md)", shown, ", ".join(became) or "nothing published")


def _apply_cameras(layers: _Layers, value: Any, shown: str, base_dir: Path) -> None:
    if not isinstance(value, dict) or not value:
        raise ConfigError(f"{shown}: cameras: must hold [cameras.NAME] tables, got {_type_name(value)}")
    for cam_name, table in value.items():
        if not re.fullmatch(CAMERA_NAME, cam_name):
            raise ConfigError(f"{shown}: cameras.{cam_name}: camera names are a letter then letters, digits, "
                              "_ or - (at most 32)")
        if not isinstance(table, dict):
            raise ConfigError(f"{shown}: cameras.{cam_name}: must be a table [cameras.{cam_name}], "
                              f"got {_type_name(table)}")
        target = layers.add_camera(cam_name)
        for key, item in table.items():
            layers.set(shown, "camera", key, item, from_text=False, base_dir=base_dir, target=target)


def _read_sensors(value: Any, shown: str, base_dir: Path) -> list[_Entry]:
    if not isinstance(value, list) or not value or not all(isinstance(v, dict) for v in value):
        raise ConfigError(f"{shown}: sensors: must be [[sensors]] tables (one per sensor)")
    sensor_spec = {f.name: f for f in fields(SensorConfig)}
    cal_spec = {f.name: f for f in fields(CalibrationConfig) if f.name in SENSOR_CALIBRATION_KEYS}
    entries = []
    for k, table in enumerate(value):
        label = f"sensors[{k}]"
        if isinstance(table.get("id"), int) and not isinstance(table.get("id"), bool):
            label += f" (id {table['id']})"
        entry = _Entry({}, {}, label)
        for key, item in table.items():
            where = f"{shown}: {label}: {key}"
            if key in sensor_spec:
                entry.sensor[key] = _check(sensor_spec[key], "sensor", key, item, False, base_dir, where)
            elif key in cal_spec:
                entry.calibration[key] = _check(cal_spec[key], "calibration", key, item, False, base_dir, where)
            else:
                known = ", ".join((*sensor_spec, *cal_spec))
                raise ConfigError(f"{where}: unknown key (known: {known}; board-wide calibration keys go in "
                                  "[calibration])")
        if "id" not in entry.sensor:
            raise ConfigError(f"{shown}: {label}: id: required (0..255, what the MCU hears)")
        entries.append(entry)
    return entries


#: Variables with the prefix that are not config overrides (tools/install.sh's, the tests' soak length).
NOT_CONFIG_VARS = frozenset({"OPTITAC_PYTHON", "OPTITAC_SOAK_MINUTES"})


def _env_key(var: str) -> tuple[str, str] | None:
    """``OPTITAC_LINK_SERIAL_URL`` -> ("link", "serial_url"); None for :data:`NOT_CONFIG_VARS`.

    Raises
    ------
    ConfigError
        For a section that does not exist (``OPTITAC_LNK_TRANSPORT`` was ignored without a word).
    """
    if var in NOT_CONFIG_VARS:
        return None
    rest = var[len(ENV_PREFIX):].lower()
    section, _, key = rest.partition("_")
    if section == "publish":
        name, _, key = key.partition("_")
        if name not in PUBLISH_SECTIONS or not key:
            raise ConfigError(f"environment {var}: publishers are set as OPTITAC_PUBLISH_<NAME>_<KEY> "
                              f"(NAME: {', '.join(PUBLISH_SECTIONS)})")
        return section, f"{name}.{key}"
    if section in _LISTS:
        raise ConfigError(f"environment {var}: cameras and sensors are set in the board file "
                          "(or on the command line as cameras.NAME.KEY)")
    if section not in _SECTIONS:
        raise ConfigError(f"environment {var}: no section {section!r} (sections: {', '.join(sorted(_SECTIONS))})")
    if section == "camera" and key.startswith("options_"):
        return section, "options." + key[len("options_"):]
    return section, key


def _split_override(key: str) -> tuple[str, str]:
    section, dot, rest = key.partition(".")
    if not dot or not rest:
        raise ConfigError(f"command line: {key}: overrides are written section.key=value")
    return section, rest


def load_board_config(
    name_or_path: str | os.PathLike[str] = "sim",
    env: Mapping[str, str] | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> BoardConfig:
    """Read, layer and validate a board config.

    Parameters
    ----------
    name_or_path
        A packaged board NAME (``sim``, ``rpi5-gs``, ... see :func:`available_boards`)
        or the path of a TOML file.
    env
        Environment (default ``os.environ``): ``OPTITAC_<SECTION>_<KEY>`` variables
        override file values (text parsed to the key's type: ``0x40``, ``true``,
        ``0,1,2`` for channels; numbers in ASCII digits). A SECTION that is not a config section is
        refused (a misspelling must not go unnoticed), but for :data:`NOT_CONFIG_VARS`;
        ``OPTITAC_CAMERAS_*`` and ``OPTITAC_SENSORS_*`` are refused (those are set in the file).
    overrides
        From the command line, ``{"section.key": value}`` (e.g. ``{"camera.fps": 30}``,
        ``{"cameras.palm.fps": 30}`` for a named camera); values may be typed or text.
        They override the environment.

    Relative paths are resolved against the file's directory when set in the file,
    against the working directory when set by the environment or command line.

    Raises
    ------
    ConfigError
        One line naming the file (or variable, or "command line"), the key, and
        for a ``[[sensors]]`` entry the sensor.
    """
    env = os.environ if env is None else env
    path = resolve_board_config(name_or_path)
    shown = _display(path)
    layers = _Layers()
    data = _read_toml(path)
    description, entries = _apply_file(layers, data, shown, path.resolve().parent)
    named = sorted(t[len("cameras."):] for t in layers.values if t.startswith("cameras."))

    state_dir = env.get("STATE_DIRECTORY", "").split(":")[0]
    if state_dir and "calibration.bundle" not in layers.origins:
        layers.values["calibration"]["bundle"] = str(Path(state_dir) / "calibration.npz")

    cwd = Path.cwd()
    for var in sorted(env):
        if not var.startswith(ENV_PREFIX):
            continue
        target = _env_key(var)
        if target is None:
            continue
        section, key = target
        layers.set(f"environment {var}", section, key, env[var], from_text=True, base_dir=cwd)

    for dotted, value in (overrides or {}).items():
        if dotted.startswith("publish.") and dotted.count(".") == 1:  # publish.NAME: True turns it on, False off
            layers.publisher("command line", dotted[len("publish."):], on=bool(value))
            continue
        section, key = _split_override(dotted)
        into: str | None = None
        if section == "cameras":
            cam_name, _, key = key.partition(".")
            if cam_name not in named or not key:
                raise ConfigError(f"command line: {dotted}: no camera {cam_name!r} on this board "
                                  f"(its cameras: {', '.join(named) or 'one [camera]: write camera.KEY'})")
            section, into = "camera", f"cameras.{cam_name}"
        layers.set("command line", section, key, value, from_text=isinstance(value, str), base_dir=cwd,
                   target=into)

    sections = {name: cls(**layers.values[name]) for name, cls in _SECTIONS.items()}
    sections["camera"] = layers.camera("camera")
    config = BoardConfig(source=shown, description=description, origins=MappingProxyType(layers.origins),
                         publish=layers.publish(), **sections)
    if entries or named:
        config = _with_sensors(config, layers, entries, named, shown, state_dir)
    _check_consistency(config, shown)
    return config


def _with_sensors(config: BoardConfig, layers: _Layers, entries: list[_Entry], named: list[str], shown: str,
                  state_dir: str) -> BoardConfig:
    """The board with its ``[[sensors]]`` and ``[cameras.NAME]``; keys of the one-sensor form are refused."""
    origins = config.origins
    if not entries:
        raise ConfigError(f"{shown}: cameras: [cameras.NAME] tables need [[sensors]] entries naming them")
    for key, source in origins.items():
        section, _, rest = key.partition(".")
        if section == "sensor":
            raise ConfigError(f"{source}: {key}: this board lists [[sensors]]; set {rest} in each entry")
        if section == "calibration" and rest in SENSOR_CALIBRATION_KEYS:
            raise ConfigError(f"{source}: {key}: this board lists [[sensors]]; set {rest} per sensor in its entry")
        if section == "camera" and named:
            raise ConfigError(f"{source}: {key}: this board names its cameras ({', '.join(named)}); "
                              f"set cameras.NAME.{rest}")
    cameras = {name: layers.camera(f"cameras.{name}") for name in named}
    board_cal = {k: v for k, v in layers.values["calibration"].items() if k not in SENSOR_CALIBRATION_KEYS}
    home = Path(state_dir or DEFAULT_STATE_DIR)
    sensors = []
    for entry in entries:
        try:
            sensor = SensorConfig(**entry.sensor)
        except TypeError as exc:  # cannot happen: keys were checked against the fields
            raise ConfigError(f"{shown}: {entry.label}: {exc}") from None
        cal = {"bundle": str(home / f"calibration-{sensor.name}.npz"), **board_cal, **entry.calibration}
        sensors.append(BoardSensor(sensor, CalibrationConfig(**cal)))
    first = sensors[0]
    return replace(config, sensor=first.sensor,
                   camera=cameras.get(first.sensor.camera, config.camera if not named else CameraConfig()),
                   calibration=first.calibration, listed_sensors=tuple(sensors),
                   named_cameras=MappingProxyType(cameras))


def _check_consistency(config: BoardConfig, shown: str) -> None:
    """Rules between keys; the error names the source of the offending key."""

    def rank(source: str) -> int:
        return 2 if source == "command line" else 1 if source.startswith("environment ") else 0

    def fail(key: str, message: str, *involved: str) -> None:
        # Name the source that set the offending combination last (command line > env > file).
        sources = [config.origins.get(k, shown) for k in (key, *involved)]
        raise ConfigError(f"{max(sources, key=rank)}: {key}: {message}")

    for name, cam in config.cameras.items():
        p = f"cameras.{name}." if config.named_cameras else "camera."
        if cam.backend == "v4l2" and bool(cam.device) == bool(cam.pipeline):
            fail(p + ("device" if not cam.pipeline else "pipeline"),
                 f"backend 'v4l2' needs exactly one of {p}device and {p}pipeline", p + "backend")
        if cam.backend == "recording" and not cam.recording:
            fail(p + "recording", f"backend 'recording' needs {p}recording (a recording directory)", p + "backend")
        if cam.pipeline and cam.backend != "v4l2":
            fail(p + "pipeline", f"only the v4l2 backend takes a pipeline, not {cam.backend!r}", p + "backend")
        if cam.pipeline and "appsink" not in cam.pipeline:
            fail(p + "pipeline", "a GStreamer pipeline must end in an appsink")
        if cam.pixel_format == "yuv420" and (cam.width % 2 or cam.height % 2):
            fail(p + "pixel_format", "yuv420 needs an even width and height", p + "width", p + "height")
    mcap = config.publish.get("mcap")
    if isinstance(mcap, McapPublish) and not mcap.path:
        fail("publish.mcap.path", "required: the MCAP file to write")
    link = config.link
    if link.transport == "serial" and not link.serial_url:
        fail("link.serial_url", "required when link.transport is 'serial'", "link.transport")
    if link.transport == "can" and not link.can_channel:
        fail("link.can_channel", "required when link.transport is 'can'", "link.transport")
    _check_sensors(config, shown)


def _check_sensors(config: BoardConfig, shown: str) -> None:
    """Every sensor on a camera of the board, inside its frame, alone in its region; ids, names and bundles
    unique; every camera read by some sensor. The error names the sensor."""
    listed = bool(config.listed_sensors)

    def fail(s: BoardSensor, key: str, message: str) -> None:
        where = config.origins.get(f"sensor.{key}", shown)
        raise ConfigError(f"{where}: {s.label}: {key}: {message}" if listed else f"{where}: sensor.{key}: {message}")

    seen: list[BoardSensor] = []
    cameras = config.named_cameras or {MAIN_CAMERA: config.camera}
    for s in config.sensors:
        sensor = s.sensor
        cam = cameras.get(sensor.camera)
        if cam is None:
            fail(s, "camera", f"no camera {sensor.camera!r} on this board (its cameras: {', '.join(cameras)})")
            return
        if sensor.region:
            x, y, w, h = sensor.region
            if x + w > cam.width or y + h > cam.height:
                fail(s, "region", f"[{x}, {y}, {w}, {h}] leaves camera {sensor.camera!r}'s "
                                  f"{cam.width}x{cam.height} frame")
        for other in seen:
            o = other.sensor
            if o.id == sensor.id:
                fail(s, "id", f"{sensor.id} is also {other.label}'s (each sensor needs its own id)")
            if o.name == sensor.name:
                fail(s, "name", f"{sensor.name!r} is also sensor {o.id}'s (names must differ)")
            if s.calibration.bundle and s.calibration.bundle == other.calibration.bundle:
                fail(s, "bundle", f"{s.calibration.bundle} is also {other.label}'s bundle")
            if o.camera == sensor.camera:
                if not sensor.region or not o.region:
                    fail(s, "region", f"camera {sensor.camera!r} reads several sensors: each needs its region "
                                      f"(x, y, width, height), {other.label if sensor.region else 'this one'} "
                                      "has none")
                if _overlap(sensor.region, o.region):
                    fail(s, "region", f"{list(sensor.region)} overlaps {other.label}'s {list(o.region)} "
                                      f"on camera {sensor.camera!r}")
        seen.append(s)
    for name in config.named_cameras:
        if not config.sensors_of(name):
            raise ConfigError(f"{shown}: cameras.{name}: no sensor reads this camera (set camera = "
                              f"{name!r} in a [[sensors]] entry, or remove it)")


def _overlap(a: tuple[int, ...], b: tuple[int, ...]) -> bool:
    return a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3] and b[1] < a[1] + a[3]


def describe_schema() -> str:
    """The schema as text: one line per key with its default and doc (for docs and --help)."""
    lines = []
    for name, cls in _SECTIONS.items():
        lines.append(f"[{name}]")
        for f in fields(cls):
            default = f.default_factory() if f.default_factory is not MISSING else f.default
            if isinstance(default, Mapping):
                default = dict(default)
            lines.append(f"  {f.name} = {default!r}  # {f.metadata.get('doc', '')}")
    for name, cls in PUBLISH_SECTIONS.items():
        lines.append(f"[publish.{name}]  # {(cls.__doc__ or '').split(': ', 1)[-1].strip()}")
        for f in fields(cls):
            lines.append(f"  {f.name} = {f.default!r}  # {f.metadata.get('doc', '')}")
    lines.append("[cameras.NAME]  # a board with several cameras: each takes the keys of [camera]")
    lines.append("[[sensors]]  # a board with several sensors, one entry each: the keys of [sensor] and")
    lines.append(f"  # of [calibration] {', '.join(SENSOR_CALIBRATION_KEYS)} (bundle default: "
                 f"{DEFAULT_STATE_DIR}/calibration-NAME.npz)")
    return "\n".join(lines)


__all__ = [
    "PUBLISH_SECTIONS",
    "BoardConfig",
    "BoardSensor",
    "CalibrationConfig",
    "CameraConfig",
    "FoxglovePublish",
    "LedConfig",
    "LinkConfig",
    "McapPublish",
    "NetworkConfig",
    "SensorConfig",
    "StatusConfig",
    "VirtualPublish",
    "WatchdogConfig",
    "ZenohPublish",
    "available_boards",
    "describe_schema",
    "load_board_config",
    "packaged_config_dirs",
    "resolve_board_config",
]
