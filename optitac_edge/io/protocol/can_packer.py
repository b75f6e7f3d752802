"""Messages packed for the CAN link: the DBC's frames through cantools (:class:`CanCodec`), on one sensor's
identifiers with its rolling counters."""

from __future__ import annotations

from optitac_edge.io.protocol.can_codec import COUNTER_MODULO, CanCodec, message_ids
from optitac_edge.io.protocol.messages import (
    ContactMessage,
    ContactV2Message,
    MotionMessage,
    ReleaseMessage,
    StatusMessage,
)
from optitac_edge.io.protocol.packet import Packet
from optitac_edge.io.protocol.wire import MsgType


class CanPacker:
    """A :class:`~optitac_edge.io.protocol.packet.Packer` of one sensor's CAN frames.

    Every CONTACT (the CONTACT_A/CONTACT_B pair) takes the sensor's next rolling counter (mod 16), and the
    v2 and v3 frames of the same camera frame (CONTACT2's three parts, RELEASE, MOTION) carry that pair's;
    STATUS has its own. A counter advances when a message is packed, sent or not, so the MCU sees a gap.

    Parameters
    ----------
    codec : CanCodec
        The link's DBC.
    sensor_id : int
        The sensor (its identifiers: ``message_ids(sensor_id, codec.base_id)``).

    Raises
    ------
    TransportError
        If the sensor's identifiers are not 11-bit.
    """

    def __init__(self, codec: CanCodec, sensor_id: int) -> None:
        self.codec = codec
        self.sensor_id = sensor_id
        #: The sensor's identifiers by message name.
        self.ids = message_ids(sensor_id, codec.base_id)
        self.contact_counter = 0
        #: The counter of the last CONTACT pair: the v2 and v3 frames of that camera frame carry it.
        self.frame_counter = 0
        self.status_counter = 0

    def contact(self, message: ContactMessage) -> Packet:
        counter = self.frame_counter = self.contact_counter
        self.contact_counter = (counter + 1) % COUNTER_MODULO
        a, b = self.codec.contact_payloads(message, counter)
        return Packet(MsgType.CONTACT, int(message.t_us), ((self.ids["CONTACT_A"], a), (self.ids["CONTACT_B"], b)))

    def contact2(self, message: ContactV2Message) -> Packet | None:
        """The three CONTACT2 parts of one contact; None for a message without contact (the pair says so)."""
        if message.n_contacts == 0:
            return None
        can_id = self.ids["CONTACT2"]
        parts = self.codec.contact2_payloads(message, self.frame_counter)
        return Packet(MsgType.CONTACT2, int(message.t_us), tuple((can_id, p) for p in parts))

    def release(self, message: ReleaseMessage) -> Packet:
        payload = self.codec.release_payload(message.contact_id, self.frame_counter)
        return Packet(MsgType.RELEASE, int(message.t_us), ((self.ids["RELEASE"], payload),))

    def motion(self, message: MotionMessage) -> Packet:
        payload = self.codec.motion_payload(message, self.frame_counter)
        return Packet(MsgType.MOTION, int(message.t_us), ((self.ids["MOTION"], payload),))

    def status(self, message: StatusMessage) -> Packet:
        counter = self.status_counter
        self.status_counter = (counter + 1) % COUNTER_MODULO
        return Packet(MsgType.STATUS, int(message.t_us), ((self.ids["STATUS"], self.codec.status_payload(message,
                                                                                                     counter)),))
