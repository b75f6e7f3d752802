"""A validated board: every section, its sensors and cameras, and the narrowing to one sensor."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from optitac_edge.config.sections import (
    _SECTIONS,
    MAIN_CAMERA,
    SENSOR_CALIBRATION_KEYS,
    CalibrationConfig,
    CameraConfig,
    LedConfig,
    LinkConfig,
    NetworkConfig,
    RigConfig,
    SensorConfig,
    StatusConfig,
    WatchdogConfig,
)
from optitac_edge.errors import ConfigError
from optitac_edge.io.device import BoardView

if TYPE_CHECKING:
    from optitac_edge.core.bundle import CalibrationBundle
    from optitac_edge.core.region import Region


@dataclass(frozen=True)
class BoardSensor:
    """One sensor of a board: its id, name, camera and region (``sensor``) and its calibration."""

    sensor: SensorConfig
    calibration: CalibrationConfig

    @property
    def label(self) -> str:
        """How errors and logs name it: ``sensor 2 'palm'``."""
        return f"sensor {self.sensor.id} {self.sensor.name!r}"

    @property
    def region(self) -> Region | None:
        """Where the board puts it in its camera's frame (None: the whole frame)."""
        from optitac_edge.core.region import Region  # not at import: the config loader needs no numpy

        return Region(*self.sensor.region) if self.sensor.region else None

    def check_bundle(self, bundle: CalibrationBundle, path: Path | str) -> CalibrationBundle:
        """``bundle`` (read from ``path``), when it was placed where the board puts this sensor
        (:func:`~optitac_edge.core.region.check_region`: a :class:`BundleError` otherwise)."""
        from optitac_edge.core.region import check_region

        return check_region(bundle, self.region, f"{path}: {self.label}", self.sensor.id)


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
    publish: Mapping[str, object] = field(default_factory=lambda: MappingProxyType({}))
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

    def camera_key(self, camera: str) -> str:
        """Where ``camera``'s section is in the board: ``camera`` (one-camera form) or ``cameras.NAME``."""
        return f"cameras.{camera}" if self.named_cameras else "camera"

    def view(self, key: str) -> BoardView:
        """What the device of section ``key`` (``camera``, ``cameras.NAME``, ``link``, ``led``,
        ``publish.NAME``) sees of this board: the sensors' ids, a camera's sensors' regions, the rest frames,
        the ROS 2 namespace and where each value came from."""
        camera = MAIN_CAMERA if key == "camera" else key.partition(".")[2] if key.startswith("cameras.") else ""
        return BoardView(source=self.source, key=key, sensor_ids=tuple(s.sensor.id for s in self.sensors),
                         regions=self.regions_of(camera) if camera else (),
                         rest_frames=self.calibration.rest_frames, namespace=self.network.namespace,
                         origins=self.origins)

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
