"""The values of every section and key, with where each came from, layered in precedence order."""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import Field, fields
from pathlib import Path
from types import MappingProxyType
from typing import Any

from optitac_edge.config.sections import _LISTS, _SECTIONS, CameraConfig, publish_section
from optitac_edge.errors import ConfigError
from optitac_edge.fields import Invalid, Scalar, path_text, scalar, type_name

#: Camera options that name a file (the simulated camera's ``layout``): relative to the board file that sets
#: them, as every path of a board file (the systemd unit runs in ``/``).
PATH_OPTIONS = frozenset({"layout"})


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
        publish_section(name, source)  # a publisher of the registry
        target = f"publish.{name}"
        if on:
            self.publishers.setdefault(name, source)
            self.values.setdefault(target, {})
        else:
            self.publishers.pop(name, None)
            self.values.pop(target, None)
        return target

    def set(self, source: str, section: str, key: str, value: object, *, from_text: bool,
            base_dir: Path | None, target: str | None = None) -> None:
        if section == "publish":
            name, _, key = key.partition(".")
            target = self.publisher(source, name)
            if not key:
                raise ConfigError(f"{source}: publish.{name}: set its keys as publish.{name}.KEY")
            cls = publish_section(name, source)
            spec = {f.name: f for f in fields(cls)}
            if key not in spec:
                raise ConfigError(f"{source}: {target}.{key}: unknown key (known: {', '.join(spec) or 'none'})")
            self.values[target][key] = _check(spec[key], value, from_text, base_dir,
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
                option = scalar(value, from_text)
            except Invalid as exc:
                raise ConfigError(f"{source}: {where}: {exc}") from None
            if name in PATH_OPTIONS and isinstance(option, str) and option and base_dir is not None:
                option = _resolved(option, base_dir)  # relative to the file that set it, as every path
            self.options[target][name] = option
            self.origins[where] = source
            return
        if key not in spec:
            close = [k for k in spec if k.replace("_", "") == key.replace("_", "").lower()]
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise ConfigError(f"{source}: {where}: unknown key{hint} (known: {', '.join(spec)})")
        if key == "options":  # a whole table from a file
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: {where}: must be a table, got {type_name(value)}")
            for name, item in value.items():
                self.set(source, section, f"options.{name}", item, from_text=from_text, base_dir=base_dir,
                         target=target)
            return
        self.values[target][key] = _check(spec[key], value, from_text, base_dir,
                                          f"{source}: {where}")
        self.origins[where] = source

    def camera(self, target: str) -> CameraConfig:
        return CameraConfig(**{**self.values[target], "options": MappingProxyType(dict(self.options[target]))})

    def publish(self) -> Mapping[str, object]:
        return MappingProxyType({name: publish_section(name, source)(**self.values[f"publish.{name}"])
                                 for name, source in self.publishers.items()})


def _resolved(path: str, base_dir: Path) -> str:
    """``path`` (``~`` expanded) against ``base_dir`` unless it is absolute."""
    expanded = Path(os.path.expanduser(path))
    return str(expanded if expanded.is_absolute() else base_dir / expanded)


def _check(spec: Field[Any], value: object, from_text: bool, base_dir: Path | None, where: str) -> object:
    """``value`` checked by ``spec``'s checker (paths resolved against ``base_dir``); errors name ``where``."""
    try:
        converted = spec.metadata["check"](value, from_text)
    except Invalid as exc:
        raise ConfigError(f"{where}: {exc}") from None
    if spec.metadata["check"] is path_text and converted and base_dir is not None:
        converted = _resolved(converted, base_dir)
    return converted
