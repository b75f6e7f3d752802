"""Messages packed for the serial link: the wire tables' payloads (:mod:`~optitac_edge.io.protocol.wire`,
:mod:`~optitac_edge.io.protocol.wire_v2`), one frame each."""

from __future__ import annotations

import logging
from collections.abc import Callable

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

_CONTACT, _CONTACT2, _RELEASE, _MOTION, _STATUS = (MsgType.CONTACT, MsgType.CONTACT2, MsgType.RELEASE, MsgType.MOTION,
                                                   MsgType.STATUS)
_contact_payload, _status_payload = wire.contact_payload, wire.status_payload
_contact2_payload, _release_payload, _motion_payload = (wire_v2.contact2_payload, wire_v2.release_payload,
                                                        wire_v2.motion_payload)


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

    def _failed(self, kind: MsgType) -> Packet | None:
        """A message that cannot be encoded: logged with its traceback, counted, nothing sent."""
        log.exception("%s not encodable", kind.name)
        if self._on_error is not None:
            self._on_error()
        return None

    # one call per message (the frame loop's): each kind written out, its payload function bound once

    def contact(self, message: ContactMessage) -> Packet | None:
        try:
            return Packet(_CONTACT, int(message.t_us), ((0, _contact_payload(message)),))
        except Exception:  # noqa: BLE001 - logged with its traceback and counted by _failed
            return self._failed(_CONTACT)

    def contact2(self, message: ContactV2Message) -> Packet | None:
        try:
            return Packet(_CONTACT2, int(message.t_us), ((0, _contact2_payload(message)),))
        except Exception:  # noqa: BLE001 - logged with its traceback and counted by _failed
            return self._failed(_CONTACT2)

    def release(self, message: ReleaseMessage) -> Packet | None:
        try:
            return Packet(_RELEASE, int(message.t_us), ((0, _release_payload(message)),))
        except Exception:  # noqa: BLE001 - logged with its traceback and counted by _failed
            return self._failed(_RELEASE)

    def motion(self, message: MotionMessage) -> Packet | None:
        try:
            return Packet(_MOTION, int(message.t_us), ((0, _motion_payload(message)),))
        except Exception:  # noqa: BLE001 - logged with its traceback and counted by _failed
            return self._failed(_MOTION)

    def status(self, message: StatusMessage) -> Packet | None:
        try:
            return Packet(_STATUS, int(message.t_us), ((0, _status_payload(message)),))
        except Exception:  # noqa: BLE001 - logged with its traceback and counted by _failed
            return self._failed(_STATUS)
