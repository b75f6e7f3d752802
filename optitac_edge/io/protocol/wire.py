"""Serial protocol v1: frame layout, CRC, COBS framing and message (de)serialisation.

Pure logic, no I/O (the transport in :mod:`optitac_edge.io.transports.serial` does the I/O).
The interface control document is ``docs/protocol.md``; keep the two in step.

A wire frame is ``COBS(header | payload | crc) 0x00`` with, little-endian::

    header  u8 version (=1) | u8 type | u16 seq | u32 t_us     (8 bytes)
    crc     u16 CRC-16/CCITT-FALSE over header and payload    (2 bytes)
"""

from __future__ import annotations

import binascii
import struct
from enum import IntEnum
from math import floor as _floor
from typing import NamedTuple

from cobs import cobs

from optitac_edge.io.protocol.messages import (
    PROTOCOL_VERSIONS,
    Command,
    CommandType,
    ContactFlags,
    ContactMessage,
    ContactV2Message,
    ResultCode,
    ShapeCode,
    StatusMessage,
    fold_angle_deg,
)

VERSION = 1
HEADER = struct.Struct("<BBHI")
CRC = struct.Struct("<H")
HEADER_SIZE = HEADER.size  # 8
CRC_SIZE = CRC.size  # 2
MIN_FRAME = HEADER_SIZE + CRC_SIZE  # 10 decoded bytes: an empty payload
#: Longest COBS-encoded frame accepted, delimiter excluded (decoded <= 63 bytes, payload <= 53).
MAX_ENCODED = 64
MAX_DECODED = MAX_ENCODED - 1
MAX_PAYLOAD = MAX_DECODED - MIN_FRAME
DELIMITER = b"\x00"


class MsgType(IntEnum):
    """Message types on the wire (sensor -> MCU: 0x00-0x0F and 0x70-0x7F; MCU -> sensor: 0x10-0x6F)."""

    CONTACT = 0x01
    STATUS = 0x02
    CONTACT2 = 0x03  # protocol v2 (wire_v2)
    RELEASE = 0x04  # protocol v2 (wire_v2)
    MOTION = 0x05  # protocol v3 (wire_v2)
    PING = 0x10
    TARE = 0x11
    STREAM = 0x12
    SET_THRESHOLD = 0x13
    SET_PROTOCOL = 0x14
    ACK = 0x7F


def is_sensor_type(msg_type: int) -> bool:
    """True for types only the sensor sends (never answered when received: no ACK storms)."""
    return msg_type < 0x10 or msg_type >= 0x70


# -- payload layouts ---------------------------------------------------------------------------

#: sensor_id, flags, x, y, major, minor, angle, strength, shape, confidence, age_us
CONTACT = struct.Struct("<BBhhHHhHBBH")
#: sensor_id, state, fps_x10, frames_dropped, camera_errors, link_errors, cpu_temp_c_x10, calibration_id
STATUS = struct.Struct("<BBHIIIhI")
#: seq acknowledged, result code
ACK = struct.Struct("<HB")
STREAM = struct.Struct("<BB")  # on (0/1), rate divider (1..255)
SET_THRESHOLD = struct.Struct("<H")  # contact-on level, 0.0001 relative units
SET_PROTOCOL = struct.Struct("<B")  # the protocol version the MCU asks for (1, 2 or 3)

COMMAND_LENGTHS = {
    CommandType.PING: 0,
    CommandType.TARE: 0,
    CommandType.STREAM: STREAM.size,
    CommandType.SET_THRESHOLD: SET_THRESHOLD.size,
    CommandType.SET_PROTOCOL: SET_PROTOCOL.size,
}

# -- scaling (wire LSB in physical units) ----------------------------------------------------

MM_LSB = 0.01  # x, y, major, minor
ANGLE_LSB = 0.01  # degrees
ANGLE_MAX = 9000  # ±90.00°
STRENGTH_LSB = 0.01  # pipeline strength (m00, relative units · mm²) per LSB
CONFIDENCE_MAX = 255
THRESHOLD_MIN = 10  # 0.0010 relative units
THRESHOLD_MAX = 5000  # 0.5000 relative units
RATE_DIVIDER_MIN = 1
RATE_DIVIDER_MAX = 255
CONTACT_FLAGS_MASK = 0x1F  # bits 5-7 reserved, sent as 0
STATE_MASK = 0xFF  # STATUS state bit 6: protocol v2 (never set on v1), bit 7: protocol v3 (never set on v1, v2)

U8, U16, U32 = 0xFF, 0xFFFF, 0xFFFFFFFF


class ProtocolError(ValueError):
    """A payload does not fit its type (wrong length or type); never raised by the decoder itself."""


class Frame(NamedTuple):
    """A frame that passed COBS, length, CRC and version checks."""

    type: int
    seq: int
    t_us: int
    payload: bytes


class Ack(NamedTuple):
    seq_acked: int
    result: int


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor)."""
    return binascii.crc_hqx(data, 0xFFFF)


def encode_frame(msg_type: int, seq: int, t_us: int, payload: bytes = b"") -> bytes:
    """The full wire frame: COBS(header | payload | crc) + 0x00. seq and t_us wrap."""
    if len(payload) > MAX_PAYLOAD:
        raise ProtocolError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    body = HEADER.pack(VERSION, msg_type & U8, seq & U16, t_us & U32) + payload
    return cobs.encode(body + CRC.pack(crc16(body))) + DELIMITER


# -- quantisation ------------------------------------------------------------------------------


def quantise(value: float, lsb: float, lo: int, hi: int) -> int:
    """value/lsb rounded half away from zero, saturated to [lo, hi]; NaN -> 0.

    Per message field of every frame, so in the fewest steps: the two saturating comparisons first (an
    infinity saturates there; NaN fails both), then NaN; a value strictly inside rounds into [lo, hi].
    """
    x = float(value) / lsb
    if x >= hi:
        return hi
    if x <= lo:
        return lo
    if x != x:  # noqa: PLR0124 - NaN, the one float unequal to itself (no call per field)
        return 0
    return _floor(x + 0.5) if x >= 0 else -_floor(0.5 - x)


def clamp_int(value: float, lo: int, hi: int) -> int:
    """``value`` truncated toward zero, saturated to [lo, hi]; NaN -> lo."""
    v = float(value)
    if v != v:  # noqa: PLR0124 - NaN, the one float unequal to itself (no call per field)
        return lo
    if v >= hi:
        return hi
    if v <= lo:
        return lo
    return int(v)


def geometry_ints(msg: ContactMessage | ContactV2Message) -> tuple[int, int, int, int, int, int]:
    """x, y, major, minor (0.01 mm), angle (0.01°, folded into ±90°) and strength (0.01) of a contact
    message as wire integers (quantised and saturated), in that order (CONTACT and CONTACT2 alike)."""
    return (quantise(msg.x_mm, MM_LSB, -32768, 32767), quantise(msg.y_mm, MM_LSB, -32768, 32767),
            quantise(msg.major_mm, MM_LSB, 0, U16), quantise(msg.minor_mm, MM_LSB, 0, U16),
            quantise(fold_angle_deg(msg.angle_deg), ANGLE_LSB, -ANGLE_MAX, ANGLE_MAX),
            quantise(msg.strength, STRENGTH_LSB, 0, U16))


def contact_payload(msg: ContactMessage, sensor_id: int | None = None) -> bytes:
    """The 18-byte CONTACT payload of ``msg`` (quantised with rounding and saturation);
    ``sensor_id`` overrides the message's."""
    return CONTACT.pack(
        clamp_int(msg.sensor_id if sensor_id is None else sensor_id, 0, U8),
        int(msg.flags) & CONTACT_FLAGS_MASK,
        *geometry_ints(msg),
        ShapeCode.coerce(msg.shape),
        quantise(msg.confidence, 1.0 / CONFIDENCE_MAX, 0, CONFIDENCE_MAX),
        clamp_int(msg.age_us, 0, U16),
    )


def status_payload(msg: StatusMessage, sensor_id: int | None = None) -> bytes:
    """The 22-byte STATUS payload of ``msg`` (counters saturate at 2^32-1); ``sensor_id``
    overrides the message's."""
    return STATUS.pack(
        clamp_int(msg.sensor_id if sensor_id is None else sensor_id, 0, U8),
        int(msg.state) & STATE_MASK,
        clamp_int(msg.fps_x10, 0, U16),
        clamp_int(msg.frames_dropped, 0, U32),
        clamp_int(msg.camera_errors, 0, U32),
        clamp_int(msg.link_errors, 0, U32),
        clamp_int(msg.cpu_temp_c_x10, -32768, 32767),
        int(msg.calibration_id) & U32,
    )


def encode_contact(msg: ContactMessage, seq: int) -> bytes:
    """CONTACT wire frame (t_us from the message)."""
    return encode_frame(MsgType.CONTACT, seq, int(msg.t_us), contact_payload(msg))


def encode_status(msg: StatusMessage, seq: int) -> bytes:
    """STATUS wire frame (t_us from the message)."""
    return encode_frame(MsgType.STATUS, seq, int(msg.t_us), status_payload(msg))


def encode_ack(seq_acked: int, result: int, seq: int, t_us: int) -> bytes:
    """ACK wire frame answering the command whose seq is ``seq_acked``."""
    return encode_frame(MsgType.ACK, seq, t_us, ACK.pack(seq_acked & U16, int(result) & U8))


def encode_command(cmd_type: int, seq: int, t_us: int = 0, *, stream_on: bool = True,
                   rate_divider: int = 1, threshold: int = 0, version: int = 2) -> bytes:
    """A command frame as the MCU sends it (for tests, tools and MCU simulation).

    Values are packed as given (masked to their width), not range-checked, so tests can
    build out-of-range commands; ``cmd_type`` may be any byte.
    """
    if cmd_type == CommandType.STREAM:
        payload = STREAM.pack(int(stream_on) & U8, rate_divider & U8)
    elif cmd_type == CommandType.SET_THRESHOLD:
        payload = SET_THRESHOLD.pack(threshold & U16)
    elif cmd_type == CommandType.SET_PROTOCOL:
        payload = SET_PROTOCOL.pack(version & U8)
    else:
        payload = b""
    return encode_frame(cmd_type, seq, t_us, payload)


# -- decoding ----------------------------------------------------------------------------------


def _expect(payload: bytes, st: struct.Struct, name: str) -> tuple:
    if len(payload) != st.size:
        raise ProtocolError(f"{name} payload of {len(payload)} bytes, expected {st.size}")
    return st.unpack(payload)


def contact_fields(payload: bytes) -> tuple[int, ...]:
    """The raw wire integers of a CONTACT payload (sensor_id, flags, x, y, major, minor, angle,
    strength, shape, confidence, age_us)."""
    return _expect(payload, CONTACT, "CONTACT")


def decode_contact(payload: bytes, t_us: int = 0) -> ContactMessage:
    """A CONTACT payload back in physical units (``t_us`` from the header)."""
    sid, flags, x, y, major, minor, angle, strength, shape, conf, age = contact_fields(payload)
    try:
        shape_code = ShapeCode(shape)
    except ValueError:
        shape_code = ShapeCode.UNKNOWN
    return ContactMessage(
        sensor_id=sid, flags=ContactFlags(flags & CONTACT_FLAGS_MASK), t_us=t_us,
        x_mm=x * MM_LSB, y_mm=y * MM_LSB, major_mm=major * MM_LSB, minor_mm=minor * MM_LSB,
        angle_deg=angle * ANGLE_LSB, strength=strength * STRENGTH_LSB, shape=shape_code,
        confidence=conf / CONFIDENCE_MAX, age_us=age,
    )


def decode_status(payload: bytes, t_us: int = 0) -> StatusMessage:
    sid, state, fps, dropped, cam, link, temp, cal = _expect(payload, STATUS, "STATUS")
    return StatusMessage(sensor_id=sid, t_us=t_us, fps_x10=fps, frames_dropped=dropped,
                         camera_errors=cam, link_errors=link, cpu_temp_c_x10=temp,
                         calibration_id=cal, state=state)


def decode_ack(payload: bytes) -> Ack:
    return Ack(*_expect(payload, ACK, "ACK"))


def parse_command(msg_type: int, seq: int, payload: bytes) -> Command | tuple[int, ResultCode]:
    """A validated :class:`Command`, or ``(seq, result)`` to answer with a non-zero ACK.

    Unknown type -> UNKNOWN_COMMAND, wrong payload length -> BAD_LENGTH, a value out of its
    range (STREAM on not 0/1, divider 0, threshold outside 10..5000, a protocol version other
    than 1, 2 or 3) -> OUT_OF_RANGE.
    Callers should not answer sensor-side types at all (:func:`is_sensor_type`).
    """
    try:
        ctype = CommandType(msg_type)
    except ValueError:
        return seq, ResultCode.UNKNOWN_COMMAND
    if len(payload) != COMMAND_LENGTHS[ctype]:
        return seq, ResultCode.BAD_LENGTH
    if ctype == CommandType.STREAM:
        on, div = STREAM.unpack(payload)
        if on > 1 or not RATE_DIVIDER_MIN <= div <= RATE_DIVIDER_MAX:
            return seq, ResultCode.OUT_OF_RANGE
        return Command(ctype, seq, stream_on=bool(on), rate_divider=div)
    if ctype == CommandType.SET_THRESHOLD:
        (thr,) = SET_THRESHOLD.unpack(payload)
        if not THRESHOLD_MIN <= thr <= THRESHOLD_MAX:
            return seq, ResultCode.OUT_OF_RANGE
        return Command(ctype, seq, threshold=thr)
    if ctype == CommandType.SET_PROTOCOL:
        (version,) = SET_PROTOCOL.unpack(payload)
        if version not in PROTOCOL_VERSIONS:
            return seq, ResultCode.OUT_OF_RANGE
        return Command(ctype, seq, version=version)
    return Command(ctype, seq)


def contact_csv_row(frame: Frame) -> str:
    """The line ``optitac_rx`` prints for a CONTACT frame (wire integers):
    ``seq,t_us,flags,x,y,major,minor,angle,strength,shape,confidence,age``."""
    _sid, flags, x, y, major, minor, angle, strength, shape, conf, age = contact_fields(frame.payload)
    return ",".join(str(v) for v in (frame.seq, frame.t_us, flags, x, y, major, minor, angle,
                                     strength, shape, conf, age))


CSV_HEADER = "seq,t_us,flags,x,y,major,minor,angle,strength,shape,confidence,age"
