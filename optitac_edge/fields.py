"""The board config's value checkers: each takes a value (and whether it came as text) and returns it
converted, or raises :class:`Invalid` with what is wrong; :func:`setting` attaches one to a section's field."""

from __future__ import annotations

import math
import re
import sys
from dataclasses import field
from typing import Any, Protocol, TypeVar

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10 (JetPack 6 / Ubuntu 22.04)
    import tomli as tomllib

from optitac_edge.text import parse_float, parse_int

Scalar = str | int | float | bool


class Invalid(Exception):
    """A value failed validation; the message says why (no source/key yet)."""


# --------------------------------------------------------------------------- value checkers
# A checker takes (value, from_text) and returns the converted value or raises Invalid.
# ``from_text`` is True for environment variables and string command-line overrides.

T_co = TypeVar("T_co", covariant=True)


class Checker(Protocol[T_co]):
    """``check(value, from_text)``: the value converted, or :class:`Invalid`."""

    def __call__(self, value: object, from_text: bool, /) -> T_co: ...


def show(value: object) -> str:
    return repr(value) if isinstance(value, str) else f"{value!r} ({type_name(value)})"


def type_name(value: object) -> str:
    return {bool: "boolean", int: "integer", float: "float", str: "string", list: "array",
            dict: "table"}.get(type(value), type(value).__name__)


def integer(lo: int, hi: int, what: str = "an integer") -> Checker[int]:
    def check(value: object, from_text: bool) -> int:
        if from_text and isinstance(value, str):
            try:
                value = parse_int(value)
            except ValueError:
                raise Invalid(f"must be {what} in {lo}..{hi} (ASCII digits), got {value!r}") from None
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise Invalid(f"must be {what} in {lo}..{hi}, got {show(value)}")
        return value
    return check


def number(lo: float, hi: float, *, lo_open: bool = False) -> Checker[float]:
    rng = f"{lo:g} < x <= {hi:g}" if lo_open else f"{lo:g}..{hi:g}"

    def check(value: object, from_text: bool) -> float:
        if from_text and isinstance(value, str):
            try:
                value = parse_float(value)
            except ValueError:
                raise Invalid(f"must be a number in {rng} (ASCII digits), got {value!r}") from None
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                or not ((lo < value if lo_open else lo <= value) and value <= hi):
            raise Invalid(f"must be a number in {rng}, got {show(value)}")
        return float(value)
    return check


def rate(slowest: float, hi: float) -> Checker[float]:
    """A rate: 0 (none) or ``slowest..hi`` per second (1e-300 Hz made a period no integer holds)."""
    inner = number(0, hi)

    def check(value: object, from_text: bool) -> float:
        v = inner(value, from_text)
        if 0.0 < v < slowest:
            raise Invalid(f"must be 0 (none) or a rate in {slowest:g}..{hi:g} per second, got {show(value)}")
        return v
    return check


_TRUE = {"1", "true", "yes", "on"}


_FALSE = {"0", "false", "no", "off"}


def boolean(value: object, from_text: bool) -> bool:
    if from_text and isinstance(value, str):
        text = value.strip().lower()
        if text in _TRUE:
            return True
        if text in _FALSE:
            return False
        raise Invalid(f"must be true or false, got {value!r}")
    if not isinstance(value, bool):
        raise Invalid(f"must be true or false, got {show(value)}")
    return value


def string(max_len: int = 1024, *, pattern: str | None = None, empty: bool = True) -> Checker[str]:
    def check(value: object, from_text: bool) -> str:
        if not isinstance(value, str):
            raise Invalid(f"must be a string, got {show(value)}")
        if not empty and not value:
            raise Invalid("must not be empty")
        if len(value) > max_len:
            raise Invalid(f"must be at most {max_len} characters, got {len(value)}")
        if "\x00" in value:
            raise Invalid("must not contain NUL")
        if pattern is not None and value and not re.fullmatch(pattern, value):
            raise Invalid(f"must match {pattern}, got {value!r}")
        return value
    return check


def choice(*choices: str) -> Checker[str]:
    def check(value: object, from_text: bool) -> str:
        if not isinstance(value, str) or value not in choices:
            raise Invalid(f"must be one of {', '.join(repr(c) for c in choices)}, got {show(value)}")
        return value
    return check


def path_text(value: object, from_text: bool) -> str:
    # Kept as text here; resolved against the file's directory by the loader. "" means "none".
    return string(4096)(value, from_text)


def int_list(value: object, from_text: bool, what: str) -> object:
    """Text ``'0,1,2'`` (environment, command line) as a list of integers, a tuple as a list; else ``value``."""
    if from_text and isinstance(value, str):
        try:
            return [parse_int(part) for part in value.split(",") if part.strip()]
        except ValueError:
            raise Invalid(f"must be {what}, got {value!r}") from None
    return list(value) if isinstance(value, tuple) else value


def channel_list(value: object, from_text: bool) -> tuple[int, ...]:
    value = int_list(value, from_text, "a list of channel numbers 0..15 (e.g. '0,1,2')")
    if isinstance(value, (bool, int)):
        value = [value]
    if not isinstance(value, list) or not value:
        raise Invalid(f"must be a non-empty array of channel numbers 0..15, got {show(value)}")
    for item in value:
        if isinstance(item, bool) or not isinstance(item, int) or not 0 <= item <= 15:
            raise Invalid(f"channels must be integers in 0..15, got {show(item)}")
    if len(set(value)) != len(value):
        raise Invalid(f"channels must be unique, got {value!r}")
    return tuple(value)


#: How a camera of a board is named: ``[cameras.NAME]``; a one-camera board's ``[camera]`` is "main".
CAMERA_NAME = r"[A-Za-z][A-Za-z0-9_-]{0,31}"


def region_box(value: object, from_text: bool) -> tuple[int, ...]:
    value = int_list(value, from_text, "x, y, width, height in px (e.g. '0,20,440,360')")
    if not isinstance(value, list) or len(value) not in (0, 4):
        raise Invalid(f"must be [x, y, width, height] in px, or [] for the whole frame, got {show(value)}")
    if any(isinstance(v, bool) or not isinstance(v, int) for v in value):
        raise Invalid(f"must be 4 integers [x, y, width, height], got {value!r}")
    if value and (value[0] < 0 or value[1] < 0 or value[2] < 16 or value[3] < 16):
        raise Invalid(f"needs x, y >= 0 and a width and height of at least 16 px, got {value!r}")
    return tuple(value)


def scalar(value: object, from_text: bool) -> Scalar:
    if from_text and isinstance(value, str):
        try:  # a TOML literal (number, boolean, quoted string), else the text itself
            text = value
            value = tomllib.loads(f"v = {value}")["v"]
        except tomllib.TOMLDecodeError:
            return text
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            try:  # TOML takes 30_0 as 300: a number from the environment is written plainly
                value = parse_int(text) if isinstance(value, int) else parse_float(text)
            except ValueError:
                raise Invalid(f"a number must be written with ASCII digits and no '_', got {text!r}") from None
    if not isinstance(value, (str, int, float, bool)):
        raise Invalid(f"must be a scalar (string, number or boolean), got {type_name(value)}")
    if isinstance(value, float) and not math.isfinite(value):
        raise Invalid(f"must be finite, got {value!r}")
    return value


def setting(check: Checker[object], default: object, doc: str, *, required: bool = False) -> Any:
    """A section's field: its checker, its default and a one-line doc. ``required``: the default (empty)
    is refused once the board is read (the publisher's file, say)."""
    return field(default=default, metadata={"check": check, "doc": doc, "required": required})


def endpoint_list(value: object, from_text: bool) -> tuple[str, ...]:
    if from_text and isinstance(value, str):
        value = [part.strip() for part in value.split(",") if part.strip()]
    if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
        raise Invalid(f"must be a list of Zenoh endpoints such as 'tcp/192.168.1.10:7447', got {show(value)}")
    for v in value:
        if not re.fullmatch(r"[a-z][a-z0-9-]*/\S+", v):
            raise Invalid(f"{v!r} is not a Zenoh endpoint (PROTOCOL/ADDRESS, e.g. 'tcp/192.168.1.10:7447')")
    return tuple(value)


ROS_NAME = r"[A-Za-z](_?[A-Za-z0-9])*"
