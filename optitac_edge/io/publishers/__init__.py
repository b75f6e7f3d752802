"""Publishers of contacts on the robot's network behind one interface, chosen by name, imported only when used."""

from __future__ import annotations

from typing import Any

from optitac_edge.io.publishers.base import Publisher

#: Publisher name -> "module:class" (python-can style lazy registry).
PUBLISHERS: dict[str, str] = {
    "zenoh": "optitac_edge.io.publishers.zenoh:ZenohPublisher",
    "virtual": "optitac_edge.io.publishers.virtual:VirtualPublisher",
    "mcap": "optitac_edge.io.publishers.mcap:McapPublisher",
    "foxglove": "optitac_edge.io.publishers.foxglove:FoxglovePublisher",
}


def open_publisher(name: str, **kwargs: Any) -> Publisher:
    """Open the publisher called ``name`` (``zenoh``, ``mcap``, ``foxglove`` or ``virtual``)."""
    from optitac_edge.errors import PublishError
    from optitac_edge.io.device import load_backend

    return load_backend(PUBLISHERS, name, "publisher", PublishError)(**kwargs)


__all__ = ["PUBLISHERS", "Publisher", "open_publisher"]
