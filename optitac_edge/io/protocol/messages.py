"""What the sensor tells the gripper MCU and what the MCU asks, independent of the wire.

The serial protocol (docs/protocol.md) and the CAN database (optitac.dbc) each
encode these messages in their own layout; the service loop fills them from
the pipeline's estimates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum, IntFlag
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from optitac_edge.core.contact import ContactEstimate

#: STATUS ``state`` bits (docs/protocol.md).
STATE_STREAMING = 0x01
STATE_BASELINE_READY = 0x02
STATE_DEGRADED = 0x04
STATE_CAMERA_FAULT = 0x08
STATE_LIGHT_CHANGE = 0x10  # a common-mode change of the light (LED dimming) since the last STATUS
STATE_CALIBRATION_UNSAVED = 0x20  # running on a bundle that could not be saved
STATE_PROTOCOL_V2 = 0x40  # the sensor speaks protocol v2 (the MCU asked for it with SET_PROTOCOL)
STATE_PROTOCOL_V3 = 0x80  # the sensor speaks protocol v3: v2 and each contact's MOTION (bit 6 set too)

#: The protocol versions a SET_PROTOCOL command may ask for.
PROTOCOL_VERSIONS = (1, 2, 3)

#: STATUS ``cpu_temp_c_x10`` when the temperature is unknown.
TEMP_UNKNOWN = -32768


class ContactV2Flags(IntFlag):
    """Bits of the CONTACT2 message's ``flags`` (protocol v2)."""

    CONTACT = 0x01
    CALIBRATED = 0x02
    SATURATED = 0x04
    DEGRADED = 0x08
    TOUCH = 0x10  # this contact touched in this frame
    DEPTH = 0x20  # depth_mm is calibrated
    FORCE = 0x40  # force_n is calibrated


class MotionFlags(IntFlag):
    """Bits of the MOTION message's ``flags`` (protocol v3)."""

    VELOCITY = 0x01  # vx, vy hold the contact's velocity (not in the frame it touched in, nor without contact)
    SLIDING = 0x02  # the contact slides
    SLIDE_BEGAN = 0x04  # its slide was found in this frame
    VIBRATION = 0x08  # vibration holds the frame's figure (learned)
    VIBRATING = 0x10  # the frame's vibration is above its quiet level
    VIBRATION_BEGAN = 0x20  # ... and rose above it in this frame


class ContactFlags(IntFlag):
    """Bits of the CONTACT message's ``flags``."""

    CONTACT = 0x01
    CALIBRATED = 0x02
    SATURATED = 0x04
    DEGRADED = 0x08
    MORE_CONTACTS = 0x10


_CONTACT, _CALIBRATED, _SATURATED, _DEGRADED, _MORE = (int(f) for f in (
    ContactFlags.CONTACT, ContactFlags.CALIBRATED, ContactFlags.SATURATED, ContactFlags.DEGRADED,
    ContactFlags.MORE_CONTACTS))
_TOUCH, _DEPTH, _FORCE = (int(f) for f in (ContactV2Flags.TOUCH, ContactV2Flags.DEPTH, ContactV2Flags.FORCE))
_VELOCITY, _SLIDING, _SLIDE_BEGAN, _VIBRATION, _VIBRATING, _VIBRATION_BEGAN = (int(f) for f in MotionFlags)


class ShapeCode(IntEnum):
    """Contact shape on the wire."""

    NONE = 0
    EDGE = 1
    CIRCLE = 2
    SQUARE = 3
    ELLIPSE = 4
    TRIANGLE = 5
    UNKNOWN = 255

    @classmethod
    def coerce(cls, value: object) -> int:
        """``value`` as a shape code on the wire; anything that is not one becomes UNKNOWN."""
        if type(value) is cls:  # the message's own field: no lookup (per frame)
            return int(value)
        try:
            return int(cls(int(value)))  # type: ignore[call-overload]
        except (ValueError, TypeError, OverflowError):
            return int(cls.UNKNOWN)

    @classmethod
    def from_name(cls, name: str, contact: bool) -> ShapeCode:
        if not contact:
            return cls.NONE
        code = _SHAPE_BY_NAME.get(name)
        if code is None:
            code = _SHAPE_BY_NAME[name] = cls.__members__.get(name.upper(), cls.UNKNOWN) if name else cls.UNKNOWN
        return code


#: Shape names already looked up (the model's class names: a handful), name -> code.
_SHAPE_BY_NAME: dict[str, ShapeCode] = {}
#: Every CONTACT flags value, by its integer (an IntFlag built once, not per frame).
_FLAGS = tuple(ContactFlags(i) for i in range(32))


#: x, y, major, minor, angle, strength and confidence of a message without contact.
_NO_CONTACT = (0.0,) * 7


def _frame_flags(contact: bool, calibrated: bool, saturated: bool, degraded: bool) -> int:
    """The flag bits CONTACT and CONTACT2 share (bits 0-3, the same in both)."""
    return ((_CONTACT if contact else 0) | (_CALIBRATED if calibrated else 0) | (_SATURATED if saturated else 0)
            | (_DEGRADED if degraded else 0))


def _contact_values(est: ContactEstimate) -> tuple[float, ...]:
    """x, y, major, minor, angle, strength and confidence of a contact estimate, NaN as 0."""
    isfinite = math.isfinite
    return tuple(v if isfinite(v) else 0.0 for v in (
        float(est.x_mm), float(est.y_mm), float(est.major_mm), float(est.minor_mm), float(est.angle_deg),
        float(est.strength), float(est.confidence)))


def fold_angle_deg(deg: float) -> float:
    """An axis angle folded into [−90, 90] degrees (kept as it is when already there; NaN stays NaN)."""
    d = float(deg)
    if math.isfinite(d) and not -90.0 <= d <= 90.0:
        d = (d + 90.0) % 180.0 - 90.0
    return d


class CommandType(IntEnum):
    """Message types sent by the MCU."""

    PING = 0x10
    TARE = 0x11
    STREAM = 0x12
    SET_THRESHOLD = 0x13
    SET_PROTOCOL = 0x14


class ResultCode(IntEnum):
    """ACK result codes (0 = ok)."""

    OK = 0
    UNKNOWN_COMMAND = 1
    BAD_LENGTH = 2
    OUT_OF_RANGE = 3
    BUSY = 4


@dataclass(slots=True)
class ContactMessage:
    """One processed frame's primary contact, in physical units (the encoders quantise).

    Attributes
    ----------
    sensor_id : int
        0..255, from the board config.
    flags : ContactFlags
    t_us : int
        The frame's sensor timestamp, CLOCK_MONOTONIC µs (wraps on the wire).
    x_mm, y_mm, major_mm, minor_mm : float
        Centroid and widths, mm (0 without contact).
    angle_deg : float
        Major axis, −90…90 degrees.
    strength : float
        Contact strength as the pipeline reports it (m00); quantised by the encoder.
    shape : ShapeCode
    confidence : float
        0..1 (0 when unknown).
    age_us : int
        From exposure to send, µs.
    """

    sensor_id: int = 0
    flags: ContactFlags = field(default_factory=lambda: ContactFlags(0))
    t_us: int = 0
    x_mm: float = 0.0
    y_mm: float = 0.0
    major_mm: float = 0.0
    minor_mm: float = 0.0
    angle_deg: float = 0.0
    strength: float = 0.0
    shape: ShapeCode = ShapeCode.NONE
    confidence: float = 0.0
    age_us: int = 0

    def fill(self, est: ContactEstimate, t_ns: int, now_ns: int, calibrated: bool, saturated: bool = False,
             degraded: bool = False, n_contacts: int = 1) -> ContactMessage:
        """Update in place from a frame's primary :class:`~optitac_edge.core.contact.ContactEstimate` (the frame
        has ``n_contacts``: MORE when it has others); returns self."""
        contact = bool(est.contact)
        flags = _frame_flags(contact, calibrated, saturated, degraded) | (_MORE if contact and n_contacts > 1 else 0)
        self.flags = _FLAGS[flags]
        self.t_us = t_ns // 1000
        (self.x_mm, self.y_mm, self.major_mm, self.minor_mm, self.angle_deg, self.strength,
         self.confidence) = _contact_values(est) if contact else _NO_CONTACT
        self.shape = ShapeCode.from_name(est.shape, contact)
        self.age_us = max((now_ns - t_ns) // 1000, 0)
        return self


@dataclass(slots=True)
class ContactV2Message:
    """Protocol v2: one contact of one processed frame (every contact; one message with
    ``n_contacts`` 0 when there is none), in physical units (the encoders quantise).

    Attributes
    ----------
    sensor_id : int
    flags : int
        :class:`ContactV2Flags` bits.
    t_us : int
        The frame's sensor timestamp, µs.
    frame : int
        The sensor's frame counter (the same in every message of one camera frame; wraps on the wire).
    index, n_contacts : int
        This contact's rank (0: the strongest) and the frame's number of contacts (0…4).
    contact_id : int
        1…255, stable from the contact's touch to its release; 0 without contact.
    x_mm, y_mm, major_mm, minor_mm, angle_deg, strength, shape, confidence, age_us
        As in :class:`ContactMessage`.
    depth_mm, force_n : float
        Indentation depth (mm) and normal force (N); 0 unless the DEPTH / FORCE flag is set.
    """

    sensor_id: int = 0
    flags: int = 0
    t_us: int = 0
    frame: int = 0
    index: int = 0
    n_contacts: int = 0
    contact_id: int = 0
    x_mm: float = 0.0
    y_mm: float = 0.0
    major_mm: float = 0.0
    minor_mm: float = 0.0
    angle_deg: float = 0.0
    strength: float = 0.0
    depth_mm: float = 0.0
    force_n: float = 0.0
    shape: ShapeCode = ShapeCode.NONE
    confidence: float = 0.0
    age_us: int = 0

    def fill(self, est: ContactEstimate, index: int, frame: int, n_contacts: int,  # noqa: PLR0913
             t_ns: int, now_ns: int, calibrated: bool, saturated: bool = False, degraded: bool = False,
             touch: bool | None = None) -> ContactV2Message:
        """Update in place from contact ``index`` of ``n_contacts`` of frame ``frame`` (a
        :class:`~optitac_edge.core.contact.ContactEstimate`; the primary one when there is no contact).

        ``touch``: the TOUCH flag (new to the receiver); None: the contact touched in this frame.
        """
        contact = bool(est.contact)
        isfinite = math.isfinite
        flags = _frame_flags(contact, calibrated, saturated, degraded)
        self.t_us = t_ns // 1000
        self.frame = int(frame)
        self.index = index
        if contact:
            self.n_contacts = int(n_contacts)
            self.contact_id = int(est.contact_id)
            if (est.touch_frame == frame) if touch is None else touch:
                flags |= _TOUCH
            (self.x_mm, self.y_mm, self.major_mm, self.minor_mm, self.angle_deg, self.strength,
             self.confidence) = _contact_values(est)
            depth, force = float(est.depth_mm), float(est.force_n)
            self.depth_mm = depth if isfinite(depth) else 0.0
            self.force_n = force if isfinite(force) else 0.0
            flags |= (_DEPTH if isfinite(depth) else 0) | (_FORCE if isfinite(force) else 0)
        else:
            self.n_contacts = self.contact_id = 0
            (self.x_mm, self.y_mm, self.major_mm, self.minor_mm, self.angle_deg, self.strength,
             self.confidence) = _NO_CONTACT
            self.depth_mm = self.force_n = 0.0
        self.flags = flags
        self.shape = ShapeCode.from_name(est.shape, contact)
        self.age_us = max((now_ns - t_ns) // 1000, 0)
        return self


@dataclass(slots=True)
class MotionMessage:
    """Protocol v3: the motion of the contact of the CONTACT2 before it (the same ``frame`` and ``index``), and
    the frame's vibration, in physical units (the encoders quantise).

    Attributes
    ----------
    sensor_id, flags : int
        ``flags``: :class:`MotionFlags` bits.
    t_us, frame, index, contact_id : int
        As the CONTACT2's (``contact_id`` 0 and ``index`` 0 when there is no contact).
    vx_mm_s, vy_mm_s : float
        The contact's velocity in the sensor frame, mm/s; 0 unless VELOCITY.
    slide_frame : int
        The frame its current slide was found in; 0 unless SLIDING.
    vibration : float
        The frame's fiber energy above 20 Hz in units of the sensor's noise; 0 unless VIBRATION.
    """

    sensor_id: int = 0
    flags: int = 0
    t_us: int = 0
    frame: int = 0
    index: int = 0
    contact_id: int = 0
    vx_mm_s: float = 0.0
    vy_mm_s: float = 0.0
    slide_frame: int = 0
    vibration: float = 0.0

    def fill(self, est: ContactEstimate, index: int, frame: int, t_ns: int, vibration: float, vibrating: bool,
             vibration_began: bool) -> MotionMessage:
        """Update in place from contact ``index`` of frame ``frame`` (a
        :class:`~optitac_edge.core.contact.ContactEstimate`, the primary one when there is no contact) and the
        frame's vibration."""
        isfinite = math.isfinite
        flags = 0
        self.t_us = t_ns // 1000
        self.frame = int(frame)
        self.index = index
        vx, vy = float(est.vx_mm_s), float(est.vy_mm_s)
        if est.contact and isfinite(vx) and isfinite(vy):
            flags |= _VELOCITY
            self.vx_mm_s, self.vy_mm_s = vx, vy
        else:
            self.vx_mm_s = self.vy_mm_s = 0.0
        self.contact_id = int(est.contact_id) if est.contact else 0
        if est.contact and est.sliding:
            flags |= _SLIDING | (_SLIDE_BEGAN if est.slide_frame == frame else 0)
            self.slide_frame = int(est.slide_frame)
        else:
            self.slide_frame = 0
        if isfinite(vibration):
            flags |= _VIBRATION | (_VIBRATING if vibrating else 0) | (_VIBRATION_BEGAN if vibration_began else 0)
            self.vibration = vibration
        else:
            self.vibration = 0.0
        self.flags = flags
        return self


@dataclass(slots=True)
class ReleaseMessage:
    """Protocol v2: a contact of the previous frame is gone (sent in the frame of its release).

    Attributes
    ----------
    sensor_id, contact_id : int
    t_us : int
        The releasing frame's timestamp, µs.
    frame : int
        The frame it was released in (the first without it).
    touch_frame : int
        The frame it touched in.
    """

    sensor_id: int = 0
    contact_id: int = 0
    t_us: int = 0
    frame: int = 0
    touch_frame: int = 0


@dataclass(frozen=True, slots=True)
class SensorState:
    """A sensor's state as STATUS reports it: the one place its flags are set and packed (``state``).

    Attributes
    ----------
    streaming : bool
        STREAM is on.
    baseline_ready : bool
    degraded : bool
        Some fiber is dead.
    camera_fault : bool
        A frame was skipped or failed, or the camera is being reopened, since the last STATUS.
    light_change : bool
        A common-mode change of the light (LED dimming) since the last STATUS.
    calibration_unsaved : bool
        Running on a bundle that could not be saved.
    protocol_v2 : bool
        The sensor speaks protocol v2 (the MCU asked for v2 or v3 with SET_PROTOCOL).
    protocol_v3 : bool
        The sensor speaks protocol v3 (v2 and MOTION).
    """

    streaming: bool = False
    baseline_ready: bool = False
    degraded: bool = False
    camera_fault: bool = False
    light_change: bool = False
    calibration_unsaved: bool = False
    protocol_v2: bool = False
    protocol_v3: bool = False

    @property
    def bits(self) -> int:
        """The STATUS ``state`` byte (bit0 streaming … bit6 protocol v2, bit7 protocol v3)."""
        return ((STATE_STREAMING if self.streaming else 0) | (STATE_BASELINE_READY if self.baseline_ready else 0)
                | (STATE_DEGRADED if self.degraded else 0) | (STATE_CAMERA_FAULT if self.camera_fault else 0)
                | (STATE_LIGHT_CHANGE if self.light_change else 0)
                | (STATE_CALIBRATION_UNSAVED if self.calibration_unsaved else 0)
                | (STATE_PROTOCOL_V2 if self.protocol_v2 else 0) | (STATE_PROTOCOL_V3 if self.protocol_v3 else 0))

    @classmethod
    def from_bits(cls, state: int) -> SensorState:
        """The flags of a received STATUS ``state`` byte."""
        return cls(bool(state & STATE_STREAMING), bool(state & STATE_BASELINE_READY), bool(state & STATE_DEGRADED),
                   bool(state & STATE_CAMERA_FAULT), bool(state & STATE_LIGHT_CHANGE),
                   bool(state & STATE_CALIBRATION_UNSAVED), bool(state & STATE_PROTOCOL_V2),
                   bool(state & STATE_PROTOCOL_V3))


@dataclass(slots=True)
class StatusMessage:
    """About once a second: the health of the sensor service."""

    sensor_id: int = 0
    t_us: int = 0
    fps_x10: int = 0  # frames per second × 10
    frames_dropped: int = 0
    camera_errors: int = 0
    link_errors: int = 0  # serial/CAN send errors and bad incoming frames
    cpu_temp_c_x10: int = TEMP_UNKNOWN  # °C × 10
    calibration_id: int = 0  # first 32 bits of the bundle's id
    state: int = 0  # SensorState.bits: bit0 streaming, bit1 baseline ready, bit2 degraded, bit3 camera fault …

    @property
    def flags(self) -> SensorState:
        """:attr:`state` as named flags."""
        return SensorState.from_bits(self.state)


#: SET_THRESHOLD: relative units (of the rest light) per LSB.
THRESHOLD_LSB = 1e-4


@dataclass(frozen=True, slots=True)
class Command:
    """A validated command from the MCU."""

    type: CommandType
    seq: int
    stream_on: bool = True
    rate_divider: int = 1
    threshold: int = 0
    version: int = 0  # SET_PROTOCOL

    @property
    def threshold_relative(self) -> float:
        """SET_THRESHOLD's contact-on level in relative units (0.001..0.5)."""
        return self.threshold * THRESHOLD_LSB
