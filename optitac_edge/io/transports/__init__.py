"""Links to the gripper MCU behind one interface, chosen by name (``[link] transport``), imported only when used.

Each transport reads its own ``[link]`` keys (:meth:`Transport.from_config`); adding one is a module with
its class and a line in :data:`TRANSPORTS`.
"""

from __future__ import annotations

from typing import Any

from optitac_edge.errors import TransportError
from optitac_edge.io.registry import Backend, Registry
from optitac_edge.io.transports.base import Transport, TransportCounters
from optitac_edge.io.transports.link import LinkConfig

#: Transport name -> its class (python-can style lazy registry).
TRANSPORTS: Registry[Transport] = Registry("transport", TransportError, {
    "serial": "optitac_edge.io.transports.serial:SerialTransport",
    "can": Backend("optitac_edge.io.transports.can:CanTransport", extra="can"),
    "none": "optitac_edge.io.transports.base:NullTransport",
})


def open_transport(name: str, **kwargs: Any) -> Transport:
    """Open the transport called ``name`` (``serial``, ``can`` or ``none``) with its constructor's ``kwargs``."""
    return TRANSPORTS.make(name, **kwargs)


__all__ = ["TRANSPORTS", "LinkConfig", "Transport", "TransportCounters", "open_transport"]
