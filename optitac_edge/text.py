"""Values as plain text for people (log lines, command output): never a raw Python dict or list."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def plain(value: Any) -> str:
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
