"""Publishers of contacts on the robot's network behind one interface, chosen by name, imported only when used.

Each publisher module declares its ``[publish.NAME]`` section beside its class (importable without the
publisher's optional library); adding one is that module and a line in :data:`PUBLISHERS`.
"""

from __future__ import annotations

from typing import Any

from optitac_edge.errors import PublishError
from optitac_edge.io.publishers.base import NetworkConfig, Publisher
from optitac_edge.io.registry import Backend, Registry

#: Publisher name (``[publish.NAME]``) -> its class and the extra its library comes with (python-can style).
PUBLISHERS: Registry[Publisher] = Registry("publisher", PublishError, {
    "zenoh": Backend("optitac_edge.io.publishers.zenoh:ZenohPublisher", extra="zenoh"),
    "foxglove": Backend("optitac_edge.io.publishers.foxglove:FoxglovePublisher", extra="foxglove"),
    "mcap": Backend("optitac_edge.io.publishers.mcap:McapPublisher", extra="mcap"),
    "virtual": "optitac_edge.io.publishers.virtual:VirtualPublisher",
}, group="optitac_edge.publishers")


def open_publisher(name: str, **kwargs: Any) -> Publisher:
    """Open the publisher called ``name`` (``zenoh``, ``mcap``, ``foxglove`` or ``virtual``) with its
    constructor's ``kwargs``."""
    return PUBLISHERS.make(name, **kwargs)


__all__ = ["PUBLISHERS", "NetworkConfig", "Publisher", "open_publisher"]
