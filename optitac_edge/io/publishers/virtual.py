"""A publisher that keeps what it is given: tests and dry runs without a network."""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import NamedTuple

from optitac_edge.io.device import BoardView
from optitac_edge.io.publishers.base import Publisher


@dataclass(frozen=True)
class VirtualPublish:
    """``[publish.virtual]``: kept in memory (tests)."""


class Published(NamedTuple):
    topic: str
    type_name: str
    payload: bytes
    source_ns: int


class VirtualPublisher(Publisher):
    """Records every message in :attr:`messages` (thread-safe to read with :meth:`taken`)."""

    Section = VirtualPublish

    @classmethod
    def from_config(cls, section: VirtualPublish, board: BoardView) -> VirtualPublisher:
        return cls(namespace=board.namespace)

    def __init__(self, namespace: str = "", **_settings: object) -> None:
        super().__init__()
        self.namespace = namespace
        self.topics: list[tuple[str, str]] = []
        self.messages: list[Published] = []
        self._lock = threading.Lock()

    def advertise(self, topic: str, type_name: str) -> int:
        self.topics.append((topic, type_name))
        return len(self.topics) - 1

    def publish(self, handle: int, payload: bytes, source_ns: int) -> None:
        topic, type_name = self.topics[handle]
        with self._lock:
            self.messages.append(Published(topic, type_name, payload, source_ns))

    def taken(self, topic: str | None = None) -> list[Published]:
        """A copy of the messages so far (on ``topic`` only, if given)."""
        with self._lock:
            return [m for m in self.messages if topic is None or m.topic == topic]

    @property
    def where(self) -> str:
        return "memory (virtual)"
