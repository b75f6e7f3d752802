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
    "optitac_msgs/msg/Contact": "RIHS01_48e700dca9b7e2db34bfa0061555ee77bd284e7426238f59b6f116e1d625fa84",
    "optitac_msgs/msg/Contacts": "RIHS01_e1537c7be1441112e24cad3ec38134846df71068e45affa9f5fc087bce0d3df7",
    "optitac_msgs/msg/FiberSignal": "RIHS01_b3eede3f07963d7b1583573e07524ddb55b8c37d84425c98e5cccd72167f3016",
    "optitac_msgs/msg/SensorStatus": "RIHS01_60cd59e3130ed38da4209a3ec0b2c9068f8a3fabd7db03a0ca9b36a8e394ccd2",
    # standard messages the pictures use: sensor_msgs/Image as ROS 2 Jazzy defines it, and foxglove_msgs'
    # ImageAnnotations from the definitions below (the tests recompute both)
    "sensor_msgs/msg/Image": "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "foxglove_msgs/msg/ImageAnnotations": "RIHS01_47c6c0891ba263ec1b20d9b785c4261d4bc41051cbcc01668130e36aa2dcaee3",
}

IMAGE = "sensor_msgs/msg/Image"
ANNOTATIONS = "foxglove_msgs/msg/ImageAnnotations"
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
    # Foxglove's image annotations as ROS 2 messages (foxglove_msgs), drawn over an Image by Foxglove/Lichtblick
    "foxglove_msgs/ImageAnnotations": ("foxglove_msgs/CircleAnnotation[] circles\n"
                                       "foxglove_msgs/PointsAnnotation[] points\n"
                                       "foxglove_msgs/TextAnnotation[] texts\n"),
    "foxglove_msgs/CircleAnnotation": ("builtin_interfaces/Time timestamp\nfoxglove_msgs/Point2 position\n"
                                       "float64 diameter\nfloat64 thickness\nfoxglove_msgs/Color fill_color\n"
                                       "foxglove_msgs/Color outline_color\n"),
    "foxglove_msgs/PointsAnnotation": ("uint8 UNKNOWN=0\nuint8 POINTS=1\nuint8 LINE_LOOP=2\nuint8 LINE_STRIP=3\n"
                                       "uint8 LINE_LIST=4\nbuiltin_interfaces/Time timestamp\nuint8 type\n"
                                       "foxglove_msgs/Point2[] points\nfoxglove_msgs/Color outline_color\n"
                                       "foxglove_msgs/Color[] outline_colors\nfoxglove_msgs/Color fill_color\n"
                                       "float64 thickness\n"),
    "foxglove_msgs/TextAnnotation": ("builtin_interfaces/Time timestamp\nfoxglove_msgs/Point2 position\n"
                                     "string text\nfloat64 font_size\nfoxglove_msgs/Color text_color\n"
                                     "foxglove_msgs/Color background_color\n"),
    "foxglove_msgs/Point2": "float64 x\nfloat64 y\n",
    "foxglove_msgs/Color": "float64 r\nfloat64 g\nfloat64 b\nfloat64 a\n",
}
#: The messages each message refers to, in the order a ros2msg schema lists them.
_DEPENDENCIES = {
    "Contact": (),
    "Contacts": ("std_msgs/Header", "builtin_interfaces/Time", "optitac_msgs/Contact"),
    "SensorStatus": ("std_msgs/Header", "builtin_interfaces/Time"),
    "FiberSignal": ("std_msgs/Header", "builtin_interfaces/Time"),
    "Image": ("std_msgs/Header", "builtin_interfaces/Time"),
    "ImageAnnotations": ("foxglove_msgs/CircleAnnotation", "builtin_interfaces/Time", "foxglove_msgs/Point2",
                         "foxglove_msgs/Color", "foxglove_msgs/PointsAnnotation", "foxglove_msgs/TextAnnotation"),
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
    vx_mm_s: float = math.nan
    vy_mm_s: float = math.nan
    sliding: bool = False
    slide_frame: int = -1


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
    vibration: float = math.nan
    vibrating: bool = False


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
        w.f64(c.vx_mm_s)
        w.f64(c.vy_mm_s)
        w.boolean(c.sliding)
        w.i32(c.slide_frame)
    w.u16_sequence(sample.released)
    w.f64(sample.vibration)
    w.boolean(sample.vibrating)
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
    """The CDR payload of a sensor_msgs/Image: (H, W) uint8 as ``mono8``, (H, W, 3) uint8 as ``rgb8``,
    (H, W) float32 as ``32FC1`` (little endian)."""
    h, w = frame.shape[:2]
    if frame.dtype == np.float32:
        encoding, dtype, step = "32FC1", "<f4", 4 * w
    else:
        encoding, dtype, step = ("mono8", "u1", w) if frame.ndim == 2 else ("rgb8", "u1", 3 * w)
    wr = CdrWriter()
    _header(wr, stamp_ns, frame_id)
    wr.u32(h)
    wr.u32(w)
    wr.string(encoding)
    wr.u8(0)
    wr.u32(step)
    data = np.ascontiguousarray(frame, dtype=dtype).data.cast("B")
    wr.u32(data.nbytes)  # uint8[]: its count, then the bytes (no alignment)
    return wr.payload(data)


#: RGBA colours of the overlay.
LIVE_FIBER = (0.2, 0.9, 0.3, 0.9)
DEAD_FIBER = (1.0, 0.2, 0.2, 1.0)
CONTACT = (1.0, 0.8, 0.0, 1.0)
_NONE = (0.0, 0.0, 0.0, 0.0)
POINTS, LINE_LOOP = 1, 2


@dataclass(slots=True)
class Outline:
    """A contact drawn on an image: its outline (K, 2) px and a label at ``at`` (x, y) px."""

    points: np.ndarray
    label: str
    at: tuple[float, float]


def encode_annotations(stamp_ns: int, fibers_px: np.ndarray, dead: np.ndarray, outlines: list[Outline]) -> bytes:
    """The CDR payload of a foxglove_msgs/ImageAnnotations: every fiber as a point (live green, dead red),
    every contact as a closed outline with its label."""
    sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
    w = CdrWriter()

    def time() -> None:
        w.i32(sec)
        w.u32(nanosec)

    def color(c: tuple[float, float, float, float]) -> None:
        for v in c:
            w.f64(v)

    def points(kind: int, xy: np.ndarray, c: tuple[float, float, float, float], thickness: float) -> None:
        time()
        w.u8(kind)
        w.struct_sequence(np.asarray(xy, dtype=np.float64).reshape(-1, 2), 8)  # Point2[]: (x, y) float64
        color(c)
        w.u32(0)
        color(c if kind == POINTS else _NONE)
        w.f64(thickness)

    w.u32(0)  # circles
    groups = [(POINTS, fibers_px[~dead], LIVE_FIBER, 4.0), (POINTS, fibers_px[dead], DEAD_FIBER, 6.0)]
    groups = [g for g in groups if len(g[1])] + [(LINE_LOOP, o.points, CONTACT, 2.0) for o in outlines]
    w.u32(len(groups))
    for kind, xy, c, thickness in groups:
        points(kind, xy, c, thickness)
    w.u32(len(outlines))
    for o in outlines:
        time()
        w.f64(o.at[0])
        w.f64(o.at[1])
        w.string(o.label)
        w.f64(14.0)
        color(CONTACT)
        color((0.0, 0.0, 0.0, 0.6))
    return w.payload()
