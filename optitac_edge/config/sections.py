"""The board config's sections: one frozen dataclass each, every field with its checker, default and doc."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

from optitac_edge.config.checkers import (
    CAMERA_NAME,
    ROS_NAME,
    Scalar,
    _bool,
    _camera_backend,
    _channels,
    _choice,
    _endpoints,
    _int,
    _num,
    _opt,
    _path,
    _rate,
    _region,
    _str,
)
from optitac_edge.io.cameras import MAX_QUEUE_FRAMES
from optitac_edge.io.transports import TRANSPORTS

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
    can_protocol: int = _opt(_int(1, 3), 1,
                             "can: 2 adds protocol v2's CONTACT2 and RELEASE frames (every contact with depth, "
                             "force and id) on their own ids beside the v1 frames, 3 also each contact's MOTION "
                             "(velocity, slip, vibration) (docs/can.md)")
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


@dataclass(frozen=True)
class NetworkConfig:
    """What every publisher of the board shares (``[network]``; docs/network.md)."""

    namespace: str = _opt(_str(200, pattern=f"(/{ROS_NAME})*"), "",
                          "ROS 2 namespace of the topics, e.g. '/robot1' ('' = none: /optitac/SENSOR/...)")
    signal_hz: float = _opt(_rate(0.001, 1000), 0.0, "per-fiber signal messages per second and sensor (0: none)")
    picture_hz: float = _opt(_rate(0.001, 120), 0.0,
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
