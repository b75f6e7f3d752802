"""Links to the gripper MCU behind one interface, chosen by name, imported only when used."""

from __future__ import annotations

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
    from ..device import load_backend
    from ..errors import TransportError

    return load_backend(TRANSPORTS, name, "transport", TransportError)(**kwargs)


__all__ = ["TRANSPORTS", "Transport", "TransportCounters", "open_transport"]
