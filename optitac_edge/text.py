"""Values as plain text for people (log lines, command output): never a raw Python dict or list."""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any


def plain(value: object) -> str:
    """One value: floats with 4 significant digits, sequences joined by '/', mappings as :func:`fields`."""
    if isinstance(value, bool) or value is None:
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, Mapping):
        return fields(value)
    if isinstance(value, (list, tuple)):
        return "/".join(plain(v) for v in value) if value else "none"
    return str(value)


def fields(mapping: Mapping[str, Any]) -> str:
    """``key value, key value`` with underscores as spaces: ``{"raw_rmse_mm": [0.7, 0.6]}`` ->
    ``raw rmse mm 0.7/0.6``."""
    return ", ".join(f"{str(k).replace('_', ' ')} {plain(v)}" for k, v in mapping.items())


#: A number as people type it in a config or on a command line: ASCII digits, no '_' (Python's int() and
#: float() also take '30_0' as 300 and Arabic-Indic or other Unicode digits as theirs).
_INT = re.compile(r"[+-]?(?:0[xX][0-9a-fA-F]+|0[oO][0-7]+|0[bB][01]+|[0-9]+)")
_FLOAT = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


def parse_int(text: str) -> int:
    """An integer written with ASCII digits (decimal, or ``0x``/``0o``/``0b``), spaces around allowed.

    Raises
    ------
    ValueError
        For anything else: ``30_0``, ``٣``, ``1.0``, ``''``.
    """
    t = text.strip()
    if not _INT.fullmatch(t):
        raise ValueError(f"not an integer: {text!r}")
    return int(t, 0) if t.lstrip("+-")[:2].lower() in ("0x", "0o", "0b") else int(t)


def parse_float(text: str) -> float:
    """A decimal number written with ASCII digits (``1``, ``-2.5``, ``1e-3``), spaces around allowed.

    Raises
    ------
    ValueError
        For anything else: ``30_0``, ``٣``, ``inf``, ``nan``, ``0x10``, ``''``.
    """
    t = text.strip()
    if not _FLOAT.fullmatch(t):
        raise ValueError(f"not a number: {text!r}")
    return float(t)
