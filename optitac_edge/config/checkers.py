"""The board config's value checkers: each takes a value (and whether it came as text) and returns it
converted, or raises :class:`_Bad` with what is wrong; :func:`_opt` attaches one to a section's field."""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Callable
from dataclasses import field
from typing import Any

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10 (JetPack 6 / Ubuntu 22.04)
    import tomli as tomllib

from optitac_edge.text import parse_float, parse_int

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


def _rate(slowest: float, hi: float) -> Checker:
    """A rate: 0 (none) or ``slowest..hi`` per second (1e-300 Hz made a period no integer holds)."""
    inner = _num(0, hi)

    def check(value: Any, from_text: bool) -> float:
        v = inner(value, from_text)
        if 0.0 < v < slowest:
            raise _Bad(f"must be 0 (none) or a rate in {slowest:g}..{hi:g} per second, got {_show(value)}")
        return v
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
