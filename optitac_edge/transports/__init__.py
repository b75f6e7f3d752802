"""Links to the gripper MCU behind one interface, chosen by name, imported only when used."""

from __future__ import annotations

import importlib
from typing import Any

from .base import Transport, TransportCounters

#: Transport name -> "module:class" (python-can style lazy registry).
TRANSPORTS: dict[str, str] = {
    "serial": "optitac_edge.transports.serial:SerialTransport",
    "can": "optitac_edge.transports.can:CanTransport",
    "null": "optitac_edge.transports.base:NullTransport",
}


def open_transport(name: str, **kwargs: Any) -> Transport:
    """Open the transport called ``name`` (``serial``, ``can`` or ``null``)."""
    from ..errors import TransportError

    try:
        target = TRANSPORTS[name]
    except KeyError:
        raise TransportError(f"unknown transport {name!r} (known: {', '.join(sorted(TRANSPORTS))})") from None
    module_name, class_name = target.split(":")
    cls = getattr(importlib.import_module(module_name), class_name)
    return cls(**kwargs)


__all__ = ["TRANSPORTS", "Transport", "TransportCounters", "open_transport"]
