"""A message packed for its link, and the packer that makes it: what a transport is handed.

As opendbc's ``CarController.update`` returns packed CAN frames and leaves the I/O to one loop at the edge,
the outbox (:mod:`optitac_edge.io.protocol.outbox`) packs each message of a sensor's frame with its link's
:class:`Packer` (the serial wire tables, :mod:`optitac_edge.io.protocol.serial_packer`; the CAN DBC through
cantools, :mod:`optitac_edge.io.protocol.can_packer`), and a transport has one
:meth:`~optitac_edge.io.transports.base.Transport.send` of a :class:`Packet`, as python-can's
``BusABC.send``. A new message kind touches its codec and the outbox only.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple, Protocol

from optitac_edge.io.protocol.messages import (
    ContactMessage,
    ContactV2Message,
    MotionMessage,
    ReleaseMessage,
    StatusMessage,
)

if TYPE_CHECKING:  # a run without a link imports no wire format (cobs)
    from optitac_edge.io.protocol.wire import MsgType


class Packet(NamedTuple):
    """One message in its link's bytes.

    Attributes
    ----------
    kind : MsgType
        What it is (the serial frame's type; counted and logged by kind).
    t_us : int
        The message's time, µs (the serial frame header's).
    frames : tuple of (int, bytes)
        The link frames, in order: for CAN each frame's arbitration id and data (a message may take several:
        a frame after one that failed is not sent, a part without the rest being useless); for serial one
        ``(0, payload)`` (the writer adds the header, sequence number, CRC and COBS).
    """

    kind: MsgType
    t_us: int
    frames: tuple[tuple[int, bytes], ...]


class Packer(Protocol):
    """One sensor's messages packed for one link (it may keep per-sensor state: CAN's rolling counters).
    None: nothing goes out for this message on this link."""

    def contact(self, message: ContactMessage) -> Packet | None: ...

    def contact2(self, message: ContactV2Message) -> Packet | None: ...

    def release(self, message: ReleaseMessage) -> Packet | None: ...

    def motion(self, message: MotionMessage) -> Packet | None: ...

    def status(self, message: StatusMessage) -> Packet | None: ...


#: The :class:`Packer` method that packs each message type (a new kind: its message class, a method of every
#: packer, and a line here).
PACKS: dict[type, str] = {ContactMessage: "contact", ContactV2Message: "contact2", ReleaseMessage: "release",
                          MotionMessage: "motion", StatusMessage: "status"}
