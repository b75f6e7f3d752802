"""Reading a board config: the file, the environment, the command line, layered and validated."""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, fields, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

from optitac_edge.config.board import BoardConfig, BoardSensor
from optitac_edge.config.checks import COMMAND_LINE, _check_consistency
from optitac_edge.config.files import _display, _read_toml, resolve_board_config, working_dir
from optitac_edge.config.layers import _check, _Layers
from optitac_edge.config.legacy import _apply_old_publish
from optitac_edge.config.overrides import ENV_PREFIX, _env_key, _split_override
from optitac_edge.config.sections import (
    _LISTS,
    _SECTIONS,
    DEFAULT_STATE_DIR,
    SENSOR_CALIBRATION_KEYS,
    CalibrationConfig,
    CameraConfig,
    SensorConfig,
    publish_section,
)
from optitac_edge.errors import ConfigError
from optitac_edge.fields import CAMERA_NAME, Invalid, string, type_name
from optitac_edge.io.publishers import PUBLISHERS

#: The only schema version there is.
CONFIG_VERSION = 1


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
                raise ConfigError(f"{shown}: {name}: must be a table [{name}], got {type_name(value)}")
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
                description = string(400)(value, False)
            except Invalid as exc:
                raise ConfigError(f"{shown}: description: {exc}") from None
        else:
            kind = "section" if isinstance(value, dict) else "key"
            raise ConfigError(f"{shown}: {name}: unknown {kind} (known sections: "
                              f"{', '.join((*_SECTIONS, *_LISTS))})")
    if old:
        _apply_old_publish(layers, old, shown, base_dir)
    return description, entries


def _new_publish(value: object) -> bool:
    """``[publish.NAME]`` tables (not the old form's ``[publish]`` keys)."""
    return isinstance(value, dict) and bool(value) and all(isinstance(v, dict) for v in value.values())


def _apply_publish(layers: _Layers, value: dict[str, Any], shown: str, base_dir: Path) -> None:
    for name, table in value.items():
        layers.publisher(shown, name)
        for key, item in table.items():
            layers.set(shown, "publish", f"{name}.{key}", item, from_text=False, base_dir=base_dir)


def _apply_cameras(layers: _Layers, value: object, shown: str, base_dir: Path) -> None:
    if not isinstance(value, dict) or not value:
        raise ConfigError(f"{shown}: cameras: must hold [cameras.NAME] tables, got {type_name(value)}")
    for cam_name, table in value.items():
        if not re.fullmatch(CAMERA_NAME, cam_name):
            raise ConfigError(f"{shown}: cameras.{cam_name}: camera names are a letter then letters, digits, "
                              "_ or - (at most 32)")
        if not isinstance(table, dict):
            raise ConfigError(f"{shown}: cameras.{cam_name}: must be a table [cameras.{cam_name}], "
                              f"got {type_name(table)}")
        target = layers.add_camera(cam_name)
        for key, item in table.items():
            layers.set(shown, "camera", key, item, from_text=False, base_dir=base_dir, target=target)


def _read_sensors(value: object, shown: str, base_dir: Path) -> list[_Entry]:
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
                entry.sensor[key] = _check(sensor_spec[key], item, False, base_dir, where)
            elif key in cal_spec:
                entry.calibration[key] = _check(cal_spec[key], item, False, base_dir, where)
            else:
                known = ", ".join((*sensor_spec, *cal_spec))
                raise ConfigError(f"{where}: unknown key (known: {known}; board-wide calibration keys go in "
                                  "[calibration])")
        if "id" not in entry.sensor:
            raise ConfigError(f"{shown}: {label}: id: required (0..255, what the MCU hears)")
        entries.append(entry)
    return entries


def load_board_config(
    name_or_path: str | os.PathLike[str] = "sim",
    env: Mapping[str, str] | None = None,
    overrides: Mapping[str, Any] | None = None,
    overrides_from: str = COMMAND_LINE,
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
    overrides_from
        What the overrides are called in an error's line (``"command line"``, or the API's ``"settings"``).
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

    # relative paths of the environment and the command line are the working directory's (when it was removed
    # under the process, $PWD's: a path there is then missing and said so where it is opened)
    cwd = working_dir() or Path(os.environ.get("PWD") or "/")
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
            layers.publisher(overrides_from, dotted[len("publish."):], on=bool(value))
            continue
        section, key = _split_override(dotted)
        into: str | None = None
        if section == "cameras":
            cam_name, _, key = key.partition(".")
            if cam_name not in named or not key:
                raise ConfigError(f"{overrides_from}: {dotted}: no camera {cam_name!r} on this board "
                                  f"(its cameras: {', '.join(named) or 'one [camera]: write camera.KEY'})")
            section, into = "camera", f"cameras.{cam_name}"
        layers.set(overrides_from, section, key, value, from_text=isinstance(value, str), base_dir=cwd,
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
    for name in PUBLISHERS:
        cls = publish_section(name, "the registry")
        lines.append(f"[publish.{name}]  # {(cls.__doc__ or '').split(': ', 1)[-1].strip()}")
        for f in fields(cls):
            lines.append(f"  {f.name} = {f.default!r}  # {f.metadata.get('doc', '')}")
    lines.append("[cameras.NAME]  # a board with several cameras: each takes the keys of [camera]")
    lines.append("[[sensors]]  # a board with several sensors, one entry each: the keys of [sensor] and")
    lines.append(f"  # of [calibration] {', '.join(SENSOR_CALIBRATION_KEYS)} (bundle default: "
                 f"{DEFAULT_STATE_DIR}/calibration-NAME.npz)")
    return "\n".join(lines)
