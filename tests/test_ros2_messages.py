"""optitac_msgs: the shipped definitions, their type hashes, and CDR payloads decoded by two other decoders
(rosbags, and mcap-ros2-support's), field by field."""

from __future__ import annotations

import math
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from mcap_ros2.decoder import DecoderFactory
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from optitac_edge.io.ros2 import messages as msgs
from optitac_edge.io.ros2.cdr import CdrWriter

ROOT = Path(__file__).resolve().parent.parent
ROS_PACKAGE = ROOT / "ros2" / "optitac_msgs"
MSG_DIR = ROOT / "optitac_edge" / "io" / "ros2" / "msg"


@pytest.fixture(scope="module")
def store():
    ts = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for path in sorted(MSG_DIR.glob("*.msg")):
        types.update(get_types_from_msg(path.read_text(), f"optitac_msgs/msg/{path.stem}"))
    ts.register(types)
    return ts


def test_the_ros_package_builds_the_very_definitions_the_service_encodes():
    assert (ROS_PACKAGE / "msg").resolve() == MSG_DIR.resolve()
    listed = re.findall(r'"msg/(\w+)\.msg"', (ROS_PACKAGE / "CMakeLists.txt").read_text())
    assert sorted(listed) == sorted(p.stem for p in MSG_DIR.glob("*.msg"))
    package = (ROS_PACKAGE / "package.xml").read_text()
    assert "<name>optitac_msgs</name>" in package and "<depend>std_msgs</depend>" in package
    assert "<member_of_group>rosidl_interface_packages</member_of_group>" in package


def test_type_hashes_are_what_ros2_computes_from_the_definitions(store):
    # rosbags computes REP 2011's RIHS01; checked first on a hash ROS 2 itself publishes
    assert store.hash_rihs01("std_msgs/msg/String") == \
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
    ours = {f"optitac_msgs/msg/{p.stem}" for p in MSG_DIR.glob("*.msg")}
    for name in ours:
        assert store.hash_rihs01(name) == msgs.TYPE_HASHES[name], f"{name}: update TYPE_HASHES (the .msg changed)"
    assert set(msgs.TYPE_HASHES) == ours | {msgs.IMAGE, msgs.ANNOTATIONS}
    # the standard ones from the schemas the service writes: Image's is ROS 2 Jazzy's own
    assert store.hash_rihs01(msgs.IMAGE) == msgs.TYPE_HASHES[msgs.IMAGE]
    for name in (msgs.IMAGE, msgs.ANNOTATIONS):
        own = get_typestore(Stores.EMPTY)
        own.register(get_types_from_msg(msgs.ros2msg_schema(name), name))
        assert own.hash_rihs01(name) == msgs.TYPE_HASHES[name], name


def test_the_definitions_are_package_data():
    assert msgs.msg_definition(msgs.CONTACTS) == (MSG_DIR / "Contacts.msg").read_text()
    assert msgs.dds_type_name(msgs.CONTACTS) == "optitac_msgs::msg::dds_::Contacts_"


def contact(i: int, depth: float = math.nan) -> msgs.ContactValues:
    return msgs.ContactValues(id=i, touch=i % 2 == 1, touch_frame=1000 + i, x_mm=-3.25 + i, y_mm=7.125,
                              major_mm=4.5, minor_mm=2.0 + i / 7, angle_deg=-45.0, strength=123.456,
                              depth_mm=depth, force_n=1.5 * i, shape="edge" if i else "", confidence=0.875,
                              vx_mm_s=12.5 - i, vy_mm_s=math.nan if i == 1 else -0.25, sliding=i == 2,
                              slide_frame=999 if i == 2 else -1)


SAMPLES = [
    msgs.ContactsSample(3, 0, 0, False, False, False),
    msgs.ContactsSample(255, 4_294_967_295, 2**63 + 5, True, True, False, [contact(7, depth=1.25)], [2, 65535]),
    msgs.ContactsSample(1, 123456, 987654321012, True, False, True, [contact(k) for k in range(4)], [9], 3.25, True),
]


def _decoded_equal(message, sample: msgs.ContactsSample, stamp_ns: int, frame_id: str) -> None:
    assert (message.header.stamp.sec, message.header.stamp.nanosec) == divmod(stamp_ns, 1_000_000_000)
    assert message.header.frame_id == frame_id
    assert (message.sensor_id, message.frame, message.t_ns) == (sample.sensor_id, sample.frame, sample.t_ns)
    assert (message.calibrated, message.saturated, message.degraded) == \
        (sample.calibrated, sample.saturated, sample.degraded)
    assert list(message.released) == sample.released
    assert message.vibrating == sample.vibrating and (message.vibration == sample.vibration
                                                      or math.isnan(message.vibration) and math.isnan(sample.vibration))
    assert len(message.contacts) == len(sample.contacts)
    for got, want in zip(message.contacts, sample.contacts):
        for name in msgs.ContactValues.__slots__:
            a, b = getattr(got, name), getattr(want, name)
            assert a == b or (isinstance(b, float) and math.isnan(a) and math.isnan(b)), name


@pytest.mark.parametrize("sample", SAMPLES, ids=["none", "one", "four"])
def test_contacts_decode_with_rosbags_field_for_field(store, sample):
    stamp = 1_795_000_000_123_456_789
    payload = msgs.encode_contacts(sample, stamp, "optitac_thumb")
    _decoded_equal(store.deserialize_cdr(payload, msgs.CONTACTS), sample, stamp, "optitac_thumb")
    # and the bytes are exactly what rosbags encodes from the decoded message
    assert store.serialize_cdr(store.deserialize_cdr(payload, msgs.CONTACTS), msgs.CONTACTS) == payload


class _Schema:
    def __init__(self, name: str) -> None:
        self.id, self.name, self.encoding, self.data = 1, name, "ros2msg", msgs.ros2msg_schema(name).encode()


@pytest.mark.parametrize("name", [msgs.CONTACTS, msgs.STATUS, msgs.SIGNAL, msgs.IMAGE])
def test_the_mcap_schema_is_the_definition_rosbags_reads(store, name):
    # the schema's dependencies, read back by rosbags, are the types it knows for the same names
    from rosbags.typesys.msg import get_types_from_msg as from_schema

    found = from_schema(msgs.ros2msg_schema(name), name)
    assert set(found) >= {name, "std_msgs/msg/Header", "builtin_interfaces/msg/Time"}


def test_contacts_decode_with_the_mcap_ros2_decoder(store):
    decode = DecoderFactory().decoder_for("cdr", _Schema(msgs.CONTACTS))
    sample = SAMPLES[2]
    _decoded_equal(decode(msgs.encode_contacts(sample, 5_000_000_001, "f")), sample, 5_000_000_001, "f")


def test_status_decodes_field_for_field(store):
    s = msgs.StatusSample(2, "index-1", "a1b2c3", 239.5, 10**12, 7, 3, 1, 2, 99, 4, math.nan, 2,
                          True, True, False, True, False, True)
    m = store.deserialize_cdr(msgs.encode_status(s, 1_500_000_000, "optitac_index_1"), msgs.STATUS)
    assert (m.sensor_id, m.sensor_name, m.calibration_id) == (2, "index-1", "a1b2c3")
    assert m.fps == pytest.approx(239.5) and math.isnan(m.cpu_temp_c)
    assert (m.frames, m.contacts, m.frames_dropped, m.camera_errors, m.link_errors, m.published,
            m.publish_dropped, m.protocol) == (10**12, 7, 3, 1, 2, 99, 4, 2)
    assert (m.streaming, m.baseline_ready, m.degraded, m.camera_fault, m.light_change, m.calibration_unsaved) == \
        (True, True, False, True, False, True)
    assert (m.header.stamp.sec, m.header.stamp.nanosec) == (1, 500_000_000)


def test_fiber_signal_decodes_as_arrays(store):
    rng = np.random.default_rng(0)
    x, y, sig = (rng.normal(size=217).astype(np.float32) for _ in range(3))
    dead = np.zeros(217, bool)
    dead[[5, 100]] = True
    m = store.deserialize_cdr(msgs.encode_signal(msgs.SignalSample(9, 77, x, y, sig, dead), 0, "s"), msgs.SIGNAL)
    assert (m.sensor_id, m.frame) == (9, 77)
    np.testing.assert_array_equal(m.x_mm, x)
    np.testing.assert_array_equal(m.signal, sig)
    np.testing.assert_array_equal(np.asarray(m.dead, bool), dead)


def test_cdr_aligns_from_the_end_of_the_encapsulation_header():
    w = CdrWriter()
    w.u8(1)
    w.f64(2.0)  # 7 bytes of padding: aligned to 8 counted after the 4-byte header
    w.string("ab")
    assert w.payload() == b"\x00\x01\x00\x00" + b"\x01" + b"\x00" * 7 + np.float64(2.0).tobytes() + \
        b"\x03\x00\x00\x00ab\x00"


def test_images_and_the_overlay_decode_with_their_schemas():
    store = get_typestore(Stores.EMPTY)
    for name in (msgs.IMAGE, msgs.ANNOTATIONS):
        store.register(get_types_from_msg(msgs.ros2msg_schema(name), name))
    gray = np.arange(12, dtype=np.uint8).reshape(3, 4)
    rgb = np.arange(24, dtype=np.uint8).reshape(2, 4, 3)
    surface = np.linspace(-1, 1, 6, dtype=np.float32).reshape(2, 3)
    for image, encoding, step, dtype in ((gray, "mono8", 4, np.uint8), (rgb, "rgb8", 12, np.uint8),
                                         (surface, "32FC1", 12, "<f4")):
        m = store.deserialize_cdr(msgs.encode_image(image, 7, "f"), msgs.IMAGE)
        assert (m.height, m.width, m.encoding, m.step, m.is_bigendian) == (*image.shape[:2], encoding, step, 0)
        np.testing.assert_array_equal(np.frombuffer(bytes(m.data), dtype).reshape(image.shape), image)
    fibers = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    outline = msgs.Outline(np.array([[0.0, 0.0], [4.0, 0.0], [2.0, 3.0]]), "2 circle", (2.0, 1.0))
    a = store.deserialize_cdr(msgs.encode_annotations(3_000_000_005, fibers, np.array([False, True, False]),
                                                      [outline]), msgs.ANNOTATIONS)
    assert [p.type for p in a.points] == [1, 1, 2] and len(a.circles) == 0
    assert [(q.x, q.y) for q in a.points[0].points] == [(1.0, 2.0), (5.0, 6.0)]
    assert [(q.x, q.y) for q in a.points[1].points] == [(3.0, 4.0)]  # the dead fiber, in its own colour
    assert a.points[1].outline_color.r == 1.0 and a.points[1].outline_color.g < 0.5
    assert [(q.x, q.y) for q in a.points[2].points] == [(0.0, 0.0), (4.0, 0.0), (2.0, 3.0)]
    assert a.texts[0].text == "2 circle" and (a.texts[0].position.x, a.texts[0].position.y) == (2.0, 1.0)
    assert (a.texts[0].timestamp.sec, a.texts[0].timestamp.nanosec) == (3, 5)


PARSE_IDL = """
import sys
from pathlib import Path
from rosidl_parser.definition import IdlLocator, Message
from rosidl_parser.parser import parse_idl_file
root = Path(sys.argv[1])
for f in sorted(root.rglob("*.idl")):
    m = parse_idl_file(IdlLocator(root, f.relative_to(root))).content.get_elements_of_type(Message)[0]
    print(m.structure.namespaced_type.name, ",".join(x.name for x in m.structure.members))
"""


@pytest.mark.skipif(shutil.which("rosidl") is None, reason="ROS 2's rosidl tools not installed (.ci/run installs "
                    "Debian's python3-rosidl and rosidl-tools)")
def test_ros2s_own_tools_translate_and_parse_the_definitions(tmp_path):
    """What colcon runs first on the package: rosidl_adapter (.msg -> .idl) and rosidl_parser (Debian's
    rosidl 3.3, the Humble release); a field name, type or constant ROS 2 refuses fails here."""
    files = [f"msg/{p.name}" for p in sorted(MSG_DIR.glob("*.msg"))]
    out = subprocess.run(["rosidl", "translate", "--to", "idl", "-o", str(tmp_path), "optitac_msgs", *files],
                         cwd=ROS_PACKAGE, capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 0 and "No translate extensions" not in out.stderr, out.stderr
    parsed = subprocess.run(["/usr/bin/python3", "-c", PARSE_IDL, str(tmp_path)], capture_output=True, text=True,
                            timeout=120, check=False)
    assert parsed.returncode == 0, parsed.stderr
    members = dict(line.split(" ", 1) for line in parsed.stdout.splitlines())
    assert set(members) == {"Contact", "Contacts", "FiberSignal", "SensorStatus"}
    assert members["Contact"].split(",") == list(msgs.ContactValues.__slots__)
    assert members["Contacts"].split(",")[:4] == ["header", "sensor_id", "frame", "t_ns"]
