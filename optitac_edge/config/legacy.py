"""Boards written before ``[publish.NAME]``: ``[publish] backend``/``foxglove`` and ``[mcap]``, read as the new
tables with a one-line hint."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from optitac_edge.config.layers import _Layers
from optitac_edge.errors import ConfigError
from optitac_edge.fields import show, type_name

log = logging.getLogger(__name__)


#: The old form's ``[publish]`` keys that are ``[network]``'s now.
_OLD_NETWORK_KEYS = ("namespace", "signal_hz", "picture_hz", "queue")


def _apply_old_publish(layers: _Layers, old: dict[str, Any], shown: str, base_dir: Path) -> None:
    """The old form (``[publish] backend``, ``foxglove``, the ``[mcap]`` section) read as ``[publish.NAME]`` and
    ``[network]``, with a one-line hint."""
    publish, mcap = old.get("publish", {}), old.get("mcap", {})
    for name, table in old.items():
        if not isinstance(table, dict):
            raise ConfigError(f"{shown}: {name}: must be a table [{name}], got {type_name(table)}")
    became: list[str] = []
    publish = dict(publish)
    backend = publish.pop("backend", "none")
    if backend not in ("none", "zenoh", "virtual"):
        raise ConfigError(f"{shown}: publish.backend: must be one of none, zenoh, virtual, got {show(backend)}")
    foxglove = publish.pop("foxglove", "")
    # every old key is checked as its new one is, also where the old form left it unused (a backend
    # "none" with Zenoh keys, [mcap] keys without a path): that publisher is then turned off again
    for key, item in publish.items():
        if key in _OLD_NETWORK_KEYS:
            layers.set(shown, "network", key, item, from_text=False, base_dir=base_dir)
            became.append(f"network.{key}")
        else:
            layers.set(shown, "publish", f"zenoh.{key}", item, from_text=False, base_dir=base_dir)
            if backend == "zenoh":
                became.append(f"publish.zenoh.{key}")
    if backend != "zenoh":
        layers.publisher(shown, "zenoh", on=False)
    if backend != "none":
        layers.publisher(shown, backend)
        became.insert(0, f"[publish.{backend}]")
    if foxglove:
        layers.set(shown, "publish", "foxglove.bind", foxglove, from_text=False, base_dir=base_dir)
        became.append("publish.foxglove.bind")
    for key, item in mcap.items():
        layers.set(shown, "publish", f"mcap.{key}", item, from_text=False, base_dir=base_dir)
    if mcap.get("path"):
        became.append("[publish.mcap]")
    else:
        layers.publisher(shown, "mcap", on=False)
    log.warning("%s: [publish] backend/foxglove and [mcap] are the old form, read as %s: write those "
                "(docs/network.md)", shown, ", ".join(became) or "nothing published")
