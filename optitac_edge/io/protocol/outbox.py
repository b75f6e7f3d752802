"""The messages one sensor's frame sends to the MCU, packed for its link.

As opendbc's ``CarController.update(CC, CS, now_nanos)`` returns the packed
frames to send and leaves the sending to its caller, :meth:`SensorOutbox.update`
takes a :class:`~optitac_edge.core.frame_result.FrameResult`, the
:class:`LinkState` (protocol version, streaming, rate divider) and ``now_ns``
and returns the :class:`~optitac_edge.io.protocol.packet.Packet` of each
message, packed by the link's packer; the frame loop only hands them to the
transport's one ``send``. :meth:`SensorOutbox.messages` is the same frame's
messages before packing: a function of the frame, the link and what the MCU
was told (no I/O, no clock): the property tests drive it alone. The packer may
keep state of its own (CAN's rolling counters).

Per sent frame, in this order:

* protocol v1 (or v2 beside v1): one CONTACT, the frame's primary contact;
* protocol v2: a RELEASE for every contact the MCU was told of that the tracker
  released since the last sent frame, then a CONTACT2 for every contact of the
  frame (one saying "no contact" when there is none);
* protocol v3: v2's, each CONTACT2 followed by the MOTION of the same contact
  (and the frame's vibration).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from optitac_edge.core.frame_result import FrameResult
from optitac_edge.core.options import MAX_CONTACTS
from optitac_edge.io.protocol.announce import ContactAnnouncer
from optitac_edge.io.protocol.messages import (
    ContactMessage,
    ContactV2Message,
    MotionMessage,
    ReleaseMessage,
    StatusMessage,
)
from optitac_edge.io.protocol.packet import PACKS

if TYPE_CHECKING:
    from optitac_edge.io.protocol.packet import Packer, Packet

#: A message of a sensor's frame to the MCU.
OutMessage = ContactMessage | ContactV2Message | ReleaseMessage | MotionMessage


@dataclass(slots=True)
class LinkState:
    """What the link to the MCU decides about sending, as the MCU's commands set it.

    Attributes
    ----------
    protocol : int
        The version the MCU asked for with SET_PROTOCOL (1 until it does; 3 is v2 with MOTION).
    from_start : frozenset of int
        The versions whose messages go out whatever the MCU asked (the transport's
        :attr:`~optitac_edge.io.transports.base.Transport.from_start`: CAN with ``link.can_protocol = 2``
        sends v2's beside v1's, with 3 also v3's MOTION).
    streaming : bool
        STREAM on (the default) or off.
    rate_divider : int
        Every ``rate_divider``-th processed camera frame is sent (STREAM's divider, >= 1).
    delivers : bool
        The link goes somewhere (False: ``run`` without an MCU).
    """

    protocol: int = 1
    from_start: frozenset[int] = frozenset()
    streaming: bool = True
    rate_divider: int = 1
    delivers: bool = True

    def due(self, frame_number: int) -> bool:
        """The camera frame that will be the ``frame_number``-th processed (from 1) is sent to the MCU."""
        return self.streaming and frame_number % self.rate_divider == 0 and self.delivers


class SensorOutbox:
    """One sensor's messages to the MCU, filled in place, and packed for its link.

    Parameters
    ----------
    sensor_id : int
        0..255, in every message.
    degraded : bool
        The sensor has dead fibers (every message's DEGRADED flag).
    packer : Packer, optional
        The link's packer of this sensor's messages (``transport.packer(sensor_id)``; default the serial
        wire format).
    """

    def __init__(self, sensor_id: int, degraded: bool = False, packer: Packer | None = None) -> None:
        self.sensor_id = sensor_id
        self.degraded = degraded
        self.contact = ContactMessage(sensor_id=sensor_id)
        self.contacts_v2 = [ContactV2Message(sensor_id=sensor_id) for _ in range(MAX_CONTACTS)]
        self.releases = [ReleaseMessage(sensor_id=sensor_id) for _ in range(MAX_CONTACTS)]
        self.motions = [MotionMessage(sensor_id=sensor_id) for _ in range(MAX_CONTACTS)]
        #: What the MCU was told (protocol v2's touches and releases).
        self.announcer = ContactAnnouncer()
        self._out: list[OutMessage] = []
        self._packets: list[Packet] = []
        if packer is None:
            from optitac_edge.io.protocol.serial_packer import SerialPacker

            packer = SerialPacker()
        self.packer: Packer = packer
        self._pack: dict[type, Callable[[Any], Packet | None]] = {kind: getattr(packer, name)
                                                                   for kind, name in PACKS.items()}

    def new_session(self) -> None:
        """The MCU switched protocol: every contact is news to it."""
        self.announcer.reset()

    def update(self, result: FrameResult, link: LinkState, send: bool, now_ns: int) -> list[Packet]:
        """The packets of one processed frame of this sensor (its :meth:`messages`, packed in order; a
        message its link does not carry, such as CAN's CONTACT2 without contact, has none).

        Returns
        -------
        list of Packet
            Reused: valid until the next call. Empty when ``send`` is False.
        """
        packets = self._packets
        packets.clear()
        pack = self._pack
        for message in self.messages(result, link, send, now_ns):
            packet = pack[type(message)](message)
            if packet is not None:
                packets.append(packet)
        return packets

    def status(self, message: StatusMessage) -> Packet | None:
        """The sensor's STATUS, packed for its link."""
        return self.packer.status(message)

    def messages(self, result: FrameResult, link: LinkState, send: bool, now_ns: int) -> list[OutMessage]:
        """The messages of one processed frame of this sensor.

        Parameters
        ----------
        result : FrameResult
            The sensor's frame (every processed frame, sent or not: the releases between sent frames
            are kept for the next one).
        link : LinkState
        send : bool
            The frame goes to the MCU (:meth:`LinkState.due` of the camera frame).
        now_ns : int
            The time of sending, ns (each message's age).

        Returns
        -------
        list of messages
            Reused: valid until the next call. Empty when ``send`` is False.
        """
        out = self._out
        out.clear()
        # the versions a sent frame carries: the one the MCU asked for and those sent from the start (3 is v2
        # with MOTION)
        protocol, start = link.protocol, link.from_start
        v3 = protocol == 3 or 3 in start
        v2 = v3 or protocol == 2 or 2 in start
        if v2:
            self.announcer.observe(result)
        if not send:
            return out
        est, frame, n = result.primary, result.frame, result.n_contacts
        t_ns, calibrated, saturated, degraded = result.t_ns, result.calibrated, result.saturated, self.degraded
        if protocol == 1 or 1 in start:
            out.append(self.contact.fill(est, t_ns, now_ns, calibrated, saturated, degraded, n))
        if v2:
            announcer = self.announcer
            t_us = t_ns // 1000
            for k, (cid, touch) in enumerate(announcer.announce(result)):
                r = self.releases[k]
                r.contact_id, r.touch_frame, r.frame, r.t_us = cid, touch, frame, t_us
                out.append(r)
            touched = announcer.touched
            for k in range(max(n, 1)):
                c = result.contacts[k] if n else est
                out.append(self.contacts_v2[k].fill(c, k, frame, n, t_ns, now_ns, calibrated, saturated, degraded,
                                                    touch=touched[k] if n else None))
                if v3:
                    out.append(self.motions[k].fill(c, k, frame, t_ns, result.vibration, result.vibrating,
                                                    result.vibration_began))
        return out
