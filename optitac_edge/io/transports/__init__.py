"""Links to the gripper MCU behind one interface, chosen by name (``[link] transport``), imported only when used.

Each transport reads its own ``[link]`` keys (:meth:`Transport.from_link`); adding one is a module with
its class and a line in :data:`TRANSPORTS`.
"""

from __future__ import annotations

from typing import Any

from optitac_edge.io.transports.base import Transport, TransportCounters

#: Transport name -> "module:class" (python-can style lazy registry).
TRANSPORTS: dict[str, str] = {
    "serial": "optitac_edge.io.transports.serial:SerialTransport",
    "can": "optitac_edge.io.transports.can:CanTransport",
    "none": "optitac_edge.io.transports.base:NullTransport",
}


def open_transport(name: str, **kwargs: Any) -> Transport:
    """Open the transport called ``name`` (``serial``, ``can`` or ``none``)."""
    from optitac_edge.errors import TransportError
    from optitac_edge.io.device import load_backend

    return load_backend(TRANSPORTS, name, "transport", TransportError)(**kwargs)


__all__ = ["TRANSPORTS", "Transport", "TransportCounters", "open_transport"]
