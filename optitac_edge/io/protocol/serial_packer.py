"""Messages packed for the serial link: the wire tables' payloads (:mod:`~optitac_edge.io.protocol.wire`,
:mod:`~optitac_edge.io.protocol.wire_v2`), one frame each."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from optitac_edge.io.protocol import wire, wire_v2
from optitac_edge.io.protocol.packet import Packet
from optitac_edge.io.protocol.wire import MsgType

log = logging.getLogger(__name__)


def _packs(kind: MsgType, payload_of: Callable[[Any], bytes]) -> Callable[[SerialPacker, Any], Packet | None]:
    """The packer method of one message kind: its payload in one frame; a message that cannot be encoded is
    logged with its traceback, counted and not sent. One call per message (the frame loop's)."""

    def pack(self: SerialPacker, message: Any) -> Packet | None:
        try:
            return Packet(kind, int(message.t_us), ((0, payload_of(message)),))
        except Exception:
            log.exception("%s not encodable", kind.name)
            if self._on_error is not None:
                self._on_error()
            return None

    pack.__name__ = kind.name.lower()
    return pack


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

    contact = _packs(MsgType.CONTACT, wire.contact_payload)
    contact2 = _packs(MsgType.CONTACT2, wire_v2.contact2_payload)
    release = _packs(MsgType.RELEASE, wire_v2.release_payload)
    motion = _packs(MsgType.MOTION, wire_v2.motion_payload)
    status = _packs(MsgType.STATUS, wire.status_payload)
