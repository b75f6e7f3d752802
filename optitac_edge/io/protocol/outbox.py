"""The messages one sensor's frame sends to the MCU: a pure function of the frame and the link.

As opendbc's ``CarController.update(CC, CS, now_nanos)`` returns the frames to
send and leaves the sending to its caller, :meth:`SensorOutbox.update` takes a
:class:`~optitac_edge.core.frame_result.FrameResult`, the :class:`LinkState`
(protocol version, streaming, rate divider) and ``now_ns`` and returns the
messages; the frame loop only hands them to the transport. No I/O, no clock,
no logging: the property tests drive it alone.

Per sent frame, in this order:

* protocol v1 (or v2 beside v1): one CONTACT, the frame's primary contact;
* protocol v2: a RELEASE for every contact the MCU was told of that the tracker
  released since the last sent frame, then a CONTACT2 for every contact of the
  frame (one saying "no contact" when there is none);
* protocol v3: v2's, each CONTACT2 followed by the MOTION of the same contact
  (and the frame's vibration).
"""

from __future__ import annotations

from dataclasses import dataclass

from optitac_edge.core.frame_result import FrameResult
from optitac_edge.core.options import MAX_CONTACTS
from optitac_edge.io.protocol.announce import ContactAnnouncer
from optitac_edge.io.protocol.messages import ContactMessage, ContactV2Message, MotionMessage, ReleaseMessage

#: A message of a sensor's frame to the MCU.
OutMessage = ContactMessage | ContactV2Message | ReleaseMessage | MotionMessage


@dataclass(slots=True)
class LinkState:
    """What the link to the MCU decides about sending, as the MCU's commands set it.

    Attributes
    ----------
    protocol : int
        The version the MCU asked for with SET_PROTOCOL (1 until it does; 3 is v2 with MOTION).
    v2_alongside_v1 : bool
        v2's messages go out beside v1's from the start (CAN with ``link.can_protocol = 2``).
    v3_alongside : bool
        And v3's MOTION after each CONTACT2 (CAN with ``link.can_protocol = 3``).
    streaming : bool
        STREAM on (the default) or off.
    rate_divider : int
        Every ``rate_divider``-th processed camera frame is sent (STREAM's divider, >= 1).
    delivers : bool
        The link goes somewhere (False: ``run`` without an MCU).
    """

    protocol: int = 1
    v2_alongside_v1: bool = False
    v3_alongside: bool = False
    streaming: bool = True
    rate_divider: int = 1
    delivers: bool = True

    def due(self, frame_number: int) -> bool:
        """The camera frame that will be the ``frame_number``-th processed (from 1) is sent to the MCU."""
        return self.streaming and frame_number % self.rate_divider == 0 and self.delivers


class SensorOutbox:
    """One sensor's messages to the MCU, filled in place (no allocation per frame beyond the releases).

    Parameters
    ----------
    sensor_id : int
        0..255, in every message.
    degraded : bool
        The sensor has dead fibers (every message's DEGRADED flag).
    """

    def __init__(self, sensor_id: int, degraded: bool = False) -> None:
        self.sensor_id = sensor_id
        self.degraded = degraded
        self.contact = ContactMessage(sensor_id=sensor_id)
        self.contacts_v2 = [ContactV2Message(sensor_id=sensor_id) for _ in range(MAX_CONTACTS)]
        self.releases = [ReleaseMessage(sensor_id=sensor_id) for _ in range(MAX_CONTACTS)]
        self.motions = [MotionMessage(sensor_id=sensor_id) for _ in range(MAX_CONTACTS)]
        #: What the MCU was told (protocol v2's touches and releases).
        self.announcer = ContactAnnouncer()
        self._out: list[OutMessage] = []

    def new_session(self) -> None:
        """The MCU switched protocol: every contact is news to it."""
        self.announcer.reset()

    def update(self, result: FrameResult, link: LinkState, send: bool, now_ns: int) -> list[OutMessage]:
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
        protocol, alongside = link.protocol, link.v2_alongside_v1
        v3 = protocol == 3 or link.v3_alongside
        v2 = protocol >= 2 or alongside or v3
        if v2:
            self.announcer.observe(result)
        if not send:
            return out
        est = result.primary
        t_ns, calibrated, saturated, degraded = est.t_ns, result.calibrated, result.saturated, self.degraded
        if protocol == 1 or alongside:
            out.append(self.contact.fill(est, t_ns, now_ns, calibrated, saturated, degraded))
        if v2:
            announcer = self.announcer
            t_us = t_ns // 1000
            for k, (cid, touch) in enumerate(announcer.announce(result)):
                r = self.releases[k]
                r.contact_id, r.touch_frame, r.frame, r.t_us = cid, touch, est.frame, t_us
                out.append(r)
            n = result.n_contacts
            touched = announcer.touched
            for k in range(max(n, 1)):
                c = result.contacts[k] if n else est
                out.append(self.contacts_v2[k].fill(c, k, t_ns, now_ns, calibrated, saturated, degraded,
                                                    touch=touched[k] if n else None))
                if v3:
                    out.append(self.motions[k].fill(c, k, t_ns, result.vibration, result.vibrating,
                                                    result.vibration_began))
        return out
