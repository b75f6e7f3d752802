"""optitac_msgs: their ROS 2 type names and hashes, and CDR encoders for them.

The definitions are ``msg/*.msg`` beside this module (and ``ros2/optitac_msgs`` in the
repository links to them). :data:`TYPE_HASHES` holds the RIHS01 type hashes ROS 2
computes from them; ``tests/test_ros2_messages.py`` recomputes them with ``rosbags``
from the files, so a changed definition without a new hash fails the tests.

The encoders take plain values (:class:`ContactValues`, :class:`ContactsSample`,
:class:`StatusSample`, :class:`SignalSample`), copied from the frame loop, and return
the CDR payload of the message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from importlib import resources

import numpy as np

from optitac_edge.io.ros2.cdr import CdrWriter

PACKAGE = "optitac_msgs"

#: RIHS01 type hash of each message (REP 2011), as ROS 2 computes it from msg/*.msg.
TYPE_HASHES: dict[str, str] = {
    "optitac_msgs/msg/Contact": "RIHS01_8ab4fc400876c825f9f29cc79c8408cbf547d5c8051b7330b7a0b9d1021df2f8",
    "optitac_msgs/msg/Contacts": "RIHS01_9d37f383a6d70c297aade3ada785efcbab4da1b30aac3768c41057d2896e4cfd",
    "optitac_msgs/msg/FiberSignal": "RIHS01_b3eede3f07963d7b1583573e07524ddb55b8c37d84425c98e5cccd72167f3016",
    "optitac_msgs/msg/SensorStatus": "RIHS01_60cd59e3130ed38da4209a3ec0b2c9068f8a3fabd7db03a0ca9b36a8e394ccd2",
}

IMAGE = "sensor_msgs/msg/Image"
CONTACTS = "optitac_msgs/msg/Contacts"
STATUS = "optitac_msgs/msg/SensorStatus"
SIGNAL = "optitac_msgs/msg/FiberSignal"


def msg_definition(type_name: str) -> str:
    """The text of ``msg/<Name>.msg`` for ``optitac_msgs/msg/<Name>``."""
    name = type_name.rsplit("/", 1)[-1]
    return (resources.files(__package__) / "msg" / f"{name}.msg").read_text(encoding="utf-8")


#: The standard messages optitac_msgs use (their fields as ROS 2 defines them).
_STANDARD = {
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
    "sensor_msgs/Image": ("std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
                          "uint8 is_bigendian\nuint32 step\nuint8[] data\n"),
}
#: The messages each message refers to, in the order a ros2msg schema lists them.
_DEPENDENCIES = {
    "Contact": (),
    "Contacts": ("std_msgs/Header", "builtin_interfaces/Time", "optitac_msgs/Contact"),
    "SensorStatus": ("std_msgs/Header", "builtin_interfaces/Time"),
    "FiberSignal": ("std_msgs/Header", "builtin_interfaces/Time"),
    "Image": ("std_msgs/Header", "builtin_interfaces/Time"),
}


def ros2msg_schema(type_name: str) -> str:
    """The ``ros2msg`` schema of a message (MCAP, Foxglove): its definition, then every message it uses,
    each after a line of 80 ``=`` and ``MSG: pkg/Name``."""
    pkg, _, name = type_name.split("/")
    parts = [_STANDARD.get(f"{pkg}/{name}") or msg_definition(type_name)]
    for dep in _DEPENDENCIES[name]:
        body = _STANDARD.get(dep) or msg_definition(dep.replace("/", "/msg/"))
        parts.append("=" * 80 + f"\nMSG: {dep}\n{body}")
    return "\n".join(parts)


def dds_type_name(type_name: str) -> str:
    """The type's name as rmw implementations put it on the wire: ``pkg::msg::dds_::Name_``."""
    pkg, kind, name = type_name.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


@dataclass(slots=True)
class ContactValues:
    """One contact as Contact.msg carries it (see its comments for units)."""

    id: int
    touch: bool
    touch_frame: int
    x_mm: float
    y_mm: float
    major_mm: float
    minor_mm: float
    angle_deg: float
    strength: float
    depth_mm: float
    force_n: float
    shape: str
    confidence: float


@dataclass(slots=True)
class ContactsSample:
    """Every contact of one sensor in one frame (Contacts.msg without its header)."""

    sensor_id: int
    frame: int
    t_ns: int
    calibrated: bool
    saturated: bool
    degraded: bool
    contacts: list[ContactValues] = field(default_factory=list)
    released: list[int] = field(default_factory=list)


@dataclass(slots=True)
class StatusSample:
    """SensorStatus.msg without its header."""

    sensor_id: int
    sensor_name: str
    calibration_id: str
    fps: float
    frames: int
    contacts: int
    frames_dropped: int
    camera_errors: int
    link_errors: int
    published: int
    publish_dropped: int
    cpu_temp_c: float
    protocol: int
    streaming: bool
    baseline_ready: bool
    degraded: bool
    camera_fault: bool
    light_change: bool
    calibration_unsaved: bool


@dataclass(slots=True)
class SignalSample:
    """FiberSignal.msg without its header: arrays of shape (N,)."""

    sensor_id: int
    frame: int
    x_mm: np.ndarray
    y_mm: np.ndarray
    signal: np.ndarray
    dead: np.ndarray


def _header(w: CdrWriter, stamp_ns: int, frame_id: str) -> None:
    """std_msgs/Header: builtin_interfaces/Time (int32 sec, uint32 nanosec) and frame_id."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    w.i32(sec)
    w.u32(nanosec)
    w.string(frame_id)


def encode_contacts(sample: ContactsSample, stamp_ns: int, frame_id: str) -> bytes:
    """The CDR payload of a Contacts message."""
    w = CdrWriter()
    _header(w, stamp_ns, frame_id)
    w.u8(sample.sensor_id)
    w.u32(sample.frame)
    w.u64(sample.t_ns)
    w.boolean(sample.calibrated)
    w.boolean(sample.saturated)
    w.boolean(sample.degraded)
    w.u32(len(sample.contacts))
    for c in sample.contacts:
        w.u16(c.id)
        w.boolean(c.touch)
        w.u32(c.touch_frame)
        for v in (c.x_mm, c.y_mm, c.major_mm, c.minor_mm, c.angle_deg, c.strength, c.depth_mm, c.force_n):
            w.f64(v)
        w.string(c.shape)
        w.f64(c.confidence)
    w.u16_sequence(sample.released)
    return w.payload()


def encode_status(sample: StatusSample, stamp_ns: int, frame_id: str) -> bytes:
    """The CDR payload of a SensorStatus message."""
    s = sample
    w = CdrWriter()
    _header(w, stamp_ns, frame_id)
    w.u8(s.sensor_id)
    w.string(s.sensor_name)
    w.string(s.calibration_id)
    w.f32(s.fps)
    for n in (s.frames, s.contacts, s.frames_dropped, s.camera_errors, s.link_errors, s.published,
              s.publish_dropped):
        w.u64(n)
    w.f32(s.cpu_temp_c if s.cpu_temp_c is not None else math.nan)
    w.u8(s.protocol)
    for b in (s.streaming, s.baseline_ready, s.degraded, s.camera_fault, s.light_change, s.calibration_unsaved):
        w.boolean(b)
    return w.payload()


def encode_signal(sample: SignalSample, stamp_ns: int, frame_id: str) -> bytes:
    """The CDR payload of a FiberSignal message."""
    w = CdrWriter()
    _header(w, stamp_ns, frame_id)
    w.u8(sample.sensor_id)
    w.u32(sample.frame)
    w.array_sequence(sample.x_mm, "<f4")
    w.array_sequence(sample.y_mm, "<f4")
    w.array_sequence(sample.signal, "<f4")
    w.array_sequence(np.asarray(sample.dead, dtype=bool), "u1")
    return w.payload()


def encode_image(frame: np.ndarray, stamp_ns: int, frame_id: str) -> bytes:
    """The CDR payload of a sensor_msgs/Image of a camera frame: (H, W) uint8 as ``mono8``,
    (H, W, 3) uint8 as ``rgb8``."""
    h, w = frame.shape[:2]
    encoding = "mono8" if frame.ndim == 2 else "rgb8"
    wr = CdrWriter()
    _header(wr, stamp_ns, frame_id)
    wr.u32(h)
    wr.u32(w)
    wr.string(encoding)
    wr.u8(0)
    wr.u32(w * (1 if frame.ndim == 2 else 3))
    wr.array_sequence(frame.reshape(-1), "u1")
    return wr.payload()
