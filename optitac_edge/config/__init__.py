"""Board configuration: which cameras, link, publishers, LED ring and calibration one board uses.

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
Nothing here touches hardware, and nothing beyond the standard library is needed to check a board.

The rooms: :mod:`~optitac_edge.config.sections` (the board's own sections; a device's section is declared
beside the device in :mod:`optitac_edge.io`, each field with a checker of :mod:`optitac_edge.fields`),
:mod:`~optitac_edge.config.board` (the validated :class:`BoardConfig`),
:mod:`~optitac_edge.config.files` (packaged NAMEs, reading TOML),
:mod:`~optitac_edge.config.layers` (values with their sources, in precedence order),
:mod:`~optitac_edge.config.overrides` (environment and command line),
:mod:`~optitac_edge.config.legacy` (the old ``[publish]`` and ``[mcap]`` form),
:mod:`~optitac_edge.config.checks` (rules between keys and sensors) and
:mod:`~optitac_edge.config.loader` (:func:`load_board_config`).
"""

from __future__ import annotations

from optitac_edge.config.board import BoardConfig, BoardSensor
from optitac_edge.config.files import available_boards, packaged_config_dirs, resolve_board_config
from optitac_edge.config.loader import describe_schema, load_board_config
from optitac_edge.config.sections import (
    DEFAULT_STATE_DIR,
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

__all__ = [
    "DEFAULT_STATE_DIR", "SENSOR_CALIBRATION_KEYS", "BoardConfig", "BoardSensor", "CalibrationConfig",
    "CameraConfig", "LedConfig", "LinkConfig", "NetworkConfig", "RigConfig", "SensorConfig", "StatusConfig",
    "WatchdogConfig", "available_boards", "describe_schema", "load_board_config", "packaged_config_dirs",
    "resolve_board_config",
]
