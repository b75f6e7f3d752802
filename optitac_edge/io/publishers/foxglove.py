"""Serve the messages live to Foxglove or Lichtblick (the Foxglove WebSocket protocol, via ``foxglove-sdk``).

Needs the ``foxglove`` extra, imported when this backend is opened. Every topic
is a channel with its ros2msg schema and CDR messages, the same bytes Zenoh and
MCAP get: Foxglove's Image panel shows ``/optitac/<sensor>/image`` with the
fibers and contacts of ``/optitac/<sensor>/annotations`` drawn over it, Plot and
Raw Messages the contacts. A channel nobody subscribes to costs one check.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

from optitac_edge.errors import PublishError
from optitac_edge.fields import setting, string
from optitac_edge.io.device import BoardView
from optitac_edge.io.publishers.base import Publisher

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FoxglovePublish:
    """``[publish.foxglove]``: everything live to Foxglove / Lichtblick (a WebSocket server)."""

    bind: str = setting(string(256, pattern=r"\S+:\d{1,5}", empty=False), "127.0.0.1:8765", "serve on HOST:PORT")


def parse_bind(bind: str) -> tuple[str, int]:
    """``HOST:PORT`` as (host, port); port 0 picks a free one.

    Raises
    ------
    PublishError
        When it is not HOST:PORT with a port in 0..65535.
    """
    host, sep, port = bind.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise PublishError(f"foxglove: {bind!r} is not HOST:PORT (e.g. 127.0.0.1:8765)")
    return host.strip("[]"), int(port)


class FoxglovePublisher(Publisher):
    """A Foxglove WebSocket server on ``bind`` (``HOST:PORT``) with a channel per topic."""

    Section = FoxglovePublish

    @classmethod
    def from_config(cls, section: FoxglovePublish, board: BoardView) -> FoxglovePublisher:
        """``[publish.foxglove]`` under the board's namespace."""
        return cls(section.bind, namespace=board.namespace)

    def __init__(self, bind: str = "127.0.0.1:8765", namespace: str = "", **_network: object) -> None:
        import foxglove  # not at import: the board config reads this module's section without it

        super().__init__()
        host, port = parse_bind(bind)
        self.namespace = namespace
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(name="optitac-edge", host=host, port=port, context=self._context)
        except Exception as exc:  # noqa: BLE001 - a port in use, an address not on this machine: one line
            raise PublishError(f"foxglove: cannot serve on {bind}: {' '.join(str(exc).split())}") from None
        self.host, self.port = host, int(self._server.port)
        self._channels: list[Any] = []

    @property
    def url(self) -> str:
        """The WebSocket URL to open in Foxglove or Lichtblick."""
        return f"ws://{self.host}:{self.port}"

    def advertise(self, topic: str, type_name: str) -> int:
        import foxglove

        from optitac_edge.io.ros2.messages import ros2msg_schema  # numpy: not when a board is read

        schema = foxglove.Schema(name=type_name, encoding="ros2msg", data=ros2msg_schema(type_name).encode())
        self._channels.append(foxglove.Channel(topic, schema=schema, message_encoding="cdr", context=self._context))
        return len(self._channels) - 1

    def publish(self, handle: int, payload: bytes, source_ns: int) -> None:
        channel = self._channels[handle]
        if channel.has_sinks():
            channel.log(payload, log_time=source_ns)

    @property
    def where(self) -> str:
        return f"Foxglove {self.url}"

    def _close_internal(self) -> None:
        for channel in self._channels:
            channel.close()
        self._server.stop()
