"""Rules between keys and between sensors, checked once everything is layered."""

from __future__ import annotations

from dataclasses import fields

from optitac_edge.config.board import BoardConfig, BoardSensor
from optitac_edge.config.sections import MAIN_CAMERA
from optitac_edge.errors import ConfigError

#: Where overrides come from: the command line's ``--set``-like options, or the API's ``settings=``.
COMMAND_LINE, API_SETTINGS = "command line", "settings"


def _check_consistency(config: BoardConfig, shown: str) -> None:
    """Rules between keys; the error names the source of the offending key."""

    def rank(source: str) -> int:
        return 2 if source in (COMMAND_LINE, API_SETTINGS) else 1 if source.startswith("environment ") else 0

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
    for name, section in config.publish.items():
        for f in fields(section):  # type: ignore[arg-type]  # every section is a dataclass
            if f.metadata.get("required") and not getattr(section, f.name):
                fail(f"publish.{name}.{f.name}", f"required: {f.metadata['doc']}")
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
