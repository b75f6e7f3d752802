"""The interface every network publisher implements."""

from __future__ import annotations

from abc import abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

from optitac_edge.fields import ROS_NAME, integer, rate, setting, string
from optitac_edge.io.device import BoardView, Device

if TYPE_CHECKING:
    from typing_extensions import Self


@dataclass(frozen=True)
class NetworkConfig:
    """What every publisher of the board shares (``[network]``; docs/network.md)."""

    namespace: str = setting(string(200, pattern=f"(/{ROS_NAME})*"), "",
                             "ROS 2 namespace of the topics, e.g. '/robot1' ('' = none: /optitac/SENSOR/...)")
    signal_hz: float = setting(rate(0.001, 1000), 0.0, "per-fiber signal messages per second and sensor (0: none)")
    picture_hz: float = setting(rate(0.001, 120), 0.0,
                                "each sensor's camera image, surface and overlay per second (0: none; 10 with foxglove "
                                "when left at 0)")
    queue: int = setting(integer(8, 1_000_000), 256,
                         "messages held for the publishing thread before the oldest is dropped (and counted)")


class Publisher(Device):
    """Puts encoded ROS 2 messages on a network under their topic names.

    :meth:`advertise` a topic once (a handle back), then :meth:`publish` its messages.
    Called from one thread (the service's publishing thread), never the frame loop.
    ``close()`` is idempotent and withdraws every topic.
    """

    #: The ROS 2 namespace the topics are under ("" for none), for logs.
    namespace: str = ""
    #: Its ``[publish.NAME]`` section: a frozen dataclass of :func:`~optitac_edge.fields.setting` fields,
    #: importable without the publisher's optional library (the board config is checked before it is there).
    Section: ClassVar[type]

    @classmethod
    def from_config(cls, section: Any, board: BoardView) -> Self:
        """Open it as its ``[publish.NAME]`` ``section`` says, under the ``board``'s ROS 2 namespace (every
        publisher of the registry has one; one made of others, as the fan-out, has not)."""
        raise NotImplementedError(f"{cls.__name__} is not opened from a board config")

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

    @property
    def undelivered(self) -> int:
        """Messages it took but could not deliver (a recording's failed writes); 0 by default."""
        return 0
