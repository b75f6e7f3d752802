"""Messages through a transport as the service sends them: packed by the transport's own packer (one per
sensor, kept, so CAN's rolling counters run on), then ``send``; and a serial packet read back."""

from __future__ import annotations

import weakref
from typing import Any

from optitac_edge.io.protocol import wire, wire_v2
from optitac_edge.io.protocol.packet import PACKS, Packer, Packet
from optitac_edge.io.protocol.wire import MsgType

_PACKERS: weakref.WeakKeyDictionary[Any, dict[int, Packer]] = weakref.WeakKeyDictionary()


def pack(transport: Any, message: Any) -> Packet | None:
    """``message`` packed by ``transport``'s packer of its sensor (the same packer every call)."""
    packers = _PACKERS.setdefault(transport, {})
    packer = packers.get(message.sensor_id)
    if packer is None:
        packer = packers[message.sensor_id] = transport.packer(message.sensor_id)
    return getattr(packer, PACKS[type(message)])(message)


def send_message(transport: Any, message: Any) -> None:
    """What the service does with one message: packed, then sent (nothing when the link has no frame
    for it)."""
    packet = pack(transport, message)
    if packet is not None:
        transport.send(packet)


_DECODE = {MsgType.CONTACT: wire.decode_contact, MsgType.STATUS: wire.decode_status,
           MsgType.CONTACT2: wire_v2.decode_contact2, MsgType.RELEASE: wire_v2.decode_release,
           MsgType.MOTION: wire_v2.decode_motion}


def decoded(packet: Packet) -> Any:
    """A serial packet's message, read back by the wire decoders (its values as the MCU reads them)."""
    return _DECODE[packet.kind](packet.frames[0][1], packet.t_us)
