"""Messages packed for the serial link: the wire tables' payloads (:mod:`~optitac_edge.io.protocol.wire`,
:mod:`~optitac_edge.io.protocol.wire_v2`), one frame each."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from optitac_edge.io.protocol import wire, wire_v2
from optitac_edge.io.protocol.messages import (
    ContactMessage,
    ContactV2Message,
    MotionMessage,
    ReleaseMessage,
    StatusMessage,
)
from optitac_edge.io.protocol.packet import Packet
from optitac_edge.io.protocol.wire import MsgType

log = logging.getLogger(__name__)


class SerialPacker:
    """A :class:`~optitac_edge.io.protocol.packet.Packer` of the serial wire format (every sensor's messages
    carry their own sensor id; the packer keeps no state).

    Parameters
    ----------
    on_error : callable, optional
        Called once per message that cannot be encoded (logged, never raised to the frame loop; the link
        counts it as a send error).
    """

    def __init__(self, on_error: Callable[[], None] | None = None) -> None:
        self._on_error = on_error

    def _pack(self, kind: MsgType, message: Any, payload_of: Callable[[Any], bytes]) -> Packet | None:
        try:
            return Packet(kind, int(message.t_us), ((0, payload_of(message)),))
        except Exception:
            log.exception("%s not encodable", kind.name)
            if self._on_error is not None:
                self._on_error()
            return None

    def contact(self, message: ContactMessage) -> Packet | None:
        return self._pack(MsgType.CONTACT, message, wire.contact_payload)

    def contact2(self, message: ContactV2Message) -> Packet | None:
        return self._pack(MsgType.CONTACT2, message, wire_v2.contact2_payload)

    def release(self, message: ReleaseMessage) -> Packet | None:
        return self._pack(MsgType.RELEASE, message, wire_v2.release_payload)

    def motion(self, message: MotionMessage) -> Packet | None:
        return self._pack(MsgType.MOTION, message, wire_v2.motion_payload)

    def status(self, message: StatusMessage) -> Packet | None:
        return self._pack(MsgType.STATUS, message, wire.status_payload)
