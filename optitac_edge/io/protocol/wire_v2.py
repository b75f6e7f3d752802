"""Serial protocol v2's messages: every contact with depth, force, id and events (docs/protocol.md §12), and
protocol v3's MOTION (§13).

Same framing as v1 (:mod:`.wire`: COBS, header with version byte 1, CRC). The
MCU asks for v2 with SET_PROTOCOL; from then on the sensor sends, per camera
frame, one RELEASE for every contact of the previous frame that is gone, then
one CONTACT2 for every contact (strongest first; one with ``n_contacts`` 0
when there is none) instead of CONTACT. STATUS and ACK are unchanged (STATUS
state bit 6 says v2 is on). With SET_PROTOCOL 3 each CONTACT2 is followed by the MOTION of the same contact
(STATUS bit 7). Pure logic, no I/O.
"""

from __future__ import annotations

import struct

from optitac_edge.io.protocol.messages import (
    ContactV2Flags,
    ContactV2Message,
    MotionFlags,
    MotionMessage,
    ReleaseMessage,
    ShapeCode,
)
from optitac_edge.io.protocol.wire import (
    ANGLE_LSB,
    CONFIDENCE_MAX,
    MM_LSB,
    STRENGTH_LSB,
    U8,
    U16,
    MsgType,
    ProtocolError,
    clamp_int,
    encode_frame,
    geometry_ints,
    quantise,
)

#: sensor_id, flags, frame, index, n_contacts, contact_id, shape, x, y, major, minor, angle, strength,
#: depth, force, confidence, reserved, age_us
CONTACT2 = struct.Struct("<BBHBBBBhhHHhHHHBBH")
#: sensor_id, contact_id, frame, touch_frame
RELEASE = struct.Struct("<BBHH")
#: sensor_id, flags, frame, index, contact_id, vx, vy, slide_frame, vibration
MOTION = struct.Struct("<BBHBBhhHH")

DEPTH_LSB = 0.001  # mm
FORCE_LSB = 0.001  # N
SPEED_LSB = 0.01  # mm/s: ±327.67 mm/s
VIBRATION_LSB = 0.01  # noise units: 0…655.35
MOTION_FLAGS_MASK = 0x3F  # bits 6, 7 reserved, sent as 0
I16_MIN, I16_MAX = -0x8000, 0x7FFF
CONTACT2_FLAGS_MASK = 0x7F  # bit 7 reserved, sent as 0
#: The wire names of CONTACT2's integers, in order (vectors, tools).
CONTACT2_KEYS = ("sensor_id", "flags", "frame", "index", "n_contacts", "contact_id", "shape", "x", "y",
                 "major", "minor", "angle", "strength", "depth", "force", "confidence", "reserved", "age_us")
RELEASE_KEYS = ("sensor_id", "contact_id", "frame", "touch_frame")
MOTION_KEYS = ("sensor_id", "flags", "frame", "index", "contact_id", "vx", "vy", "slide_frame", "vibration")


def contact2_payload(msg: ContactV2Message, sensor_id: int | None = None) -> bytes:
    """The 28-byte CONTACT2 payload of ``msg`` (quantised as v1: rounding half away from zero,
    saturation; NaN as 0); ``sensor_id`` overrides the message's."""
    return CONTACT2.pack(
        clamp_int(msg.sensor_id if sensor_id is None else sensor_id, 0, U8),
        int(msg.flags) & CONTACT2_FLAGS_MASK,
        int(msg.frame) & U16,
        clamp_int(msg.index, 0, U8),
        clamp_int(msg.n_contacts, 0, U8),
        clamp_int(msg.contact_id, 0, U8),
        ShapeCode.coerce(msg.shape),
        *geometry_ints(msg),
        quantise(msg.depth_mm, DEPTH_LSB, 0, U16),
        quantise(msg.force_n, FORCE_LSB, 0, U16),
        quantise(msg.confidence, 1.0 / CONFIDENCE_MAX, 0, CONFIDENCE_MAX),
        0,
        clamp_int(msg.age_us, 0, U16),
    )


def release_payload(msg: ReleaseMessage, sensor_id: int | None = None) -> bytes:
    """The 6-byte RELEASE payload of ``msg``; ``sensor_id`` overrides the message's."""
    return RELEASE.pack(clamp_int(msg.sensor_id if sensor_id is None else sensor_id, 0, U8),
                        clamp_int(msg.contact_id, 0, U8), int(msg.frame) & U16, int(msg.touch_frame) & U16)


def encode_contact2(msg: ContactV2Message, seq: int) -> bytes:
    """CONTACT2 wire frame (t_us from the message)."""
    return encode_frame(MsgType.CONTACT2, seq, int(msg.t_us), contact2_payload(msg))


def encode_release(msg: ReleaseMessage, seq: int) -> bytes:
    """RELEASE wire frame (t_us from the message)."""
    return encode_frame(MsgType.RELEASE, seq, int(msg.t_us), release_payload(msg))


def contact2_fields(payload: bytes) -> tuple[int, ...]:
    """The raw wire integers of a CONTACT2 payload (:data:`CONTACT2_KEYS`)."""
    if len(payload) != CONTACT2.size:
        raise ProtocolError(f"CONTACT2 payload of {len(payload)} bytes, expected {CONTACT2.size}")
    return CONTACT2.unpack(payload)


def decode_contact2(payload: bytes, t_us: int = 0) -> ContactV2Message:
    """A CONTACT2 payload back in physical units (``t_us`` from the header)."""
    (sid, flags, frame, index, n, cid, shape, x, y, major, minor, angle, strength, depth, force, conf,
     _reserved, age) = contact2_fields(payload)
    try:
        shape_code = ShapeCode(shape)
    except ValueError:
        shape_code = ShapeCode.UNKNOWN
    return ContactV2Message(
        sensor_id=sid, flags=int(ContactV2Flags(flags & CONTACT2_FLAGS_MASK)), t_us=t_us, frame=frame,
        index=index, n_contacts=n, contact_id=cid, x_mm=x * MM_LSB, y_mm=y * MM_LSB, major_mm=major * MM_LSB,
        minor_mm=minor * MM_LSB, angle_deg=angle * ANGLE_LSB, strength=strength * STRENGTH_LSB,
        depth_mm=depth * DEPTH_LSB, force_n=force * FORCE_LSB, shape=shape_code, confidence=conf / CONFIDENCE_MAX,
        age_us=age)


def decode_release(payload: bytes, t_us: int = 0) -> ReleaseMessage:
    if len(payload) != RELEASE.size:
        raise ProtocolError(f"RELEASE payload of {len(payload)} bytes, expected {RELEASE.size}")
    sid, cid, frame, touch = RELEASE.unpack(payload)
    return ReleaseMessage(sensor_id=sid, contact_id=cid, t_us=t_us, frame=frame, touch_frame=touch)


def motion_payload(msg: MotionMessage, sensor_id: int | None = None) -> bytes:
    """The 14-byte MOTION payload of ``msg`` (rounding half away from zero, saturating; NaN as 0);
    ``sensor_id`` overrides the message's."""
    return MOTION.pack(
        clamp_int(msg.sensor_id if sensor_id is None else sensor_id, 0, U8),
        int(msg.flags) & MOTION_FLAGS_MASK,
        int(msg.frame) & U16,
        clamp_int(msg.index, 0, U8),
        clamp_int(msg.contact_id, 0, U8),
        quantise(msg.vx_mm_s, SPEED_LSB, I16_MIN, I16_MAX),
        quantise(msg.vy_mm_s, SPEED_LSB, I16_MIN, I16_MAX),
        int(msg.slide_frame) & U16,
        quantise(msg.vibration, VIBRATION_LSB, 0, U16),
    )


def encode_motion(msg: MotionMessage, seq: int) -> bytes:
    """MOTION wire frame (t_us from the message)."""
    return encode_frame(MsgType.MOTION, seq, int(msg.t_us), motion_payload(msg))


def motion_fields(payload: bytes) -> tuple[int, ...]:
    """The raw wire integers of a MOTION payload (:data:`MOTION_KEYS`)."""
    if len(payload) != MOTION.size:
        raise ProtocolError(f"MOTION payload of {len(payload)} bytes, expected {MOTION.size}")
    return MOTION.unpack(payload)


def decode_motion(payload: bytes, t_us: int = 0) -> MotionMessage:
    """A MOTION payload back in physical units (``t_us`` from the header)."""
    sid, flags, frame, index, cid, vx, vy, slide_frame, vibration = motion_fields(payload)
    return MotionMessage(sensor_id=sid, flags=int(MotionFlags(flags & MOTION_FLAGS_MASK)), t_us=t_us, frame=frame,
                         index=index, contact_id=cid, vx_mm_s=vx * SPEED_LSB, vy_mm_s=vy * SPEED_LSB,
                         slide_frame=slide_frame, vibration=vibration * VIBRATION_LSB)
