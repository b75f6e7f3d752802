"""Several publishers as one: the network and an MCAP file from one publishing thread."""

from __future__ import annotations

from collections.abc import Sequence

from optitac_edge.io.publishers.base import Publisher


class FanoutPublisher(Publisher):
    """Advertises and publishes on every publisher of ``publishers`` (closes them all).

    One publisher failing does not keep the message from the others; the first
    failure is raised after every publisher had the message.
    """

    def __init__(self, publishers: Sequence[Publisher]) -> None:
        super().__init__()
        self.publishers = list(publishers)
        self.namespace = self.publishers[0].namespace if self.publishers else ""
        self._handles: list[list[int]] = []

    def advertise(self, topic: str, type_name: str) -> int:
        self._handles.append([p.advertise(topic, type_name) for p in self.publishers])
        return len(self._handles) - 1

    def publish(self, handle: int, payload: bytes, source_ns: int) -> None:
        failure: Exception | None = None
        for p, h in zip(self.publishers, self._handles[handle]):
            try:
                p.publish(h, payload, source_ns)
            except Exception as exc:  # noqa: BLE001 - raised once the others had the message
                failure = failure or exc
        if failure is not None:
            raise failure

    @property
    def where(self) -> str:
        return " and ".join(p.where for p in self.publishers)

    @property
    def summary(self) -> list[str]:
        return [line for p in self.publishers for line in p.summary]

    def _close_internal(self) -> None:
        for p in self.publishers:
            p.close()
