"""The interface every network publisher implements."""

from __future__ import annotations

from abc import abstractmethod

from optitac_edge.io.device import Device


class Publisher(Device):
    """Puts encoded ROS 2 messages on a network under their topic names.

    :meth:`advertise` a topic once (a handle back), then :meth:`publish` its messages.
    Called from one thread (the service's publishing thread), never the frame loop.
    ``close()`` is idempotent and withdraws every topic.
    """

    #: The ROS 2 namespace the topics are under ("" for none), for logs.
    namespace: str = ""

    @abstractmethod
    def advertise(self, topic: str, type_name: str) -> int:
        """Declare ``topic`` (fully qualified, e.g. ``/optitac/thumb/contacts``) carrying ``type_name``
        (e.g. ``optitac_msgs/msg/Contacts``); returns its handle."""

    @abstractmethod
    def publish(self, handle: int, payload: bytes, source_ns: int) -> None:
        """Send one CDR payload on the topic ``handle``; ``source_ns``: its time, ns since the Unix epoch."""

    @property
    def where(self) -> str:
        """A few words on where the messages go, for logs."""
        return type(self).__name__

    @property
    def summary(self) -> list[str]:
        """Lines on what was written where (a recording's files), for the run's summary; none by default."""
        return []
