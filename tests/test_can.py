"""CAN link: the packaged DBC, the cantools encoder and CanTransport on python-can's virtual bus."""

from __future__ import annotations

import errno
import itertools
import math
import time
import uuid

import can
import cantools
import pytest
from fakes.packing import send_message
from hypothesis import given, settings
from hypothesis import strategies as st

from optitac_edge.errors import TransportError
from optitac_edge.io.backoff import Backoff
from optitac_edge.io.protocol.can_codec import (
    BASE_ID,
    DBC_PATH,
    CanCodec,
    decode_frame,
    load_database,
    max_sensor_id,
    message_ids,
    split_id,
)
from optitac_edge.io.protocol.messages import ContactFlags, ContactMessage, ShapeCode, StatusMessage
from optitac_edge.io.transports import open_transport
from optitac_edge.io.transports.can import CanTransport

MM = 0.01
DEG = 0.01
CONF = 1.0 / 255.0


def _channel() -> str:
    return f"optitac-test-{uuid.uuid4().hex}"


@pytest.fixture
def link():
    """A CanTransport and a receiving bus on the same virtual channel."""
    channel = _channel()
    rx = can.Bus(channel=channel, interface="virtual")
    tx = CanTransport(channel=channel, interface="virtual", sensor_id=3, backoff_s=(0.01, 0.05))
    yield tx, rx
    tx.close()
    rx.shutdown()


def _receive(rx, n: int, timeout: float = 1.0) -> list:
    frames = []
    for _ in range(n):
        frame = rx.recv(timeout)
        assert frame is not None, f"expected {n} frames, got {len(frames)}"
        frames.append(frame)
    return frames


def _db():
    return cantools.database.load_file(str(DBC_PATH))


def _contact(**kw) -> ContactMessage:
    base = {"sensor_id": 3, "flags": ContactFlags.CONTACT | ContactFlags.CALIBRATED, "x_mm": 1.234,
            "y_mm": -5.678, "major_mm": 6.5, "minor_mm": 3.25, "angle_deg": -45.5, "strength": 12.34,
            "shape": ShapeCode.CIRCLE, "confidence": 0.8, "age_us": 1234}
    base.update(kw)
    return ContactMessage(**base)


# -- the database ------------------------------------------------------------------------------


def test_packaged_dbc_layout():
    db = _db()
    by_name = {m.name: m for m in db.messages}
    assert {n: m.frame_id for n, m in by_name.items()} == {"CONTACT_A": 0x300, "CONTACT_B": 0x301,
                                                           "STATUS": 0x302,
                                                           "CONTACT2": 0x303, "RELEASE": 0x304, "MOTION": 0x305}
    for message in db.messages:
        assert message.length == 8 and not message.is_extended_frame
        assert "COUNTER" in [s.name for s in message.signals]
        # a multiplexed message (protocol v2's CONTACT2): each PART with the common signals
        branches = sorted({v for s in message.signals for v in (s.multiplexer_ids or [])}) or [None]
        for branch in branches:
            bits = set()
            for signal in message.signals:
                if signal.multiplexer_ids is not None and branch not in signal.multiplexer_ids:
                    continue
                assert signal.byte_order == "little_endian"
                own = set(range(signal.start, signal.start + signal.length))
                assert not bits & own, f"{message.name}.{signal.name} overlaps"
                bits |= own
            if message.name in ("CONTACT_A", "CONTACT_B", "STATUS"):  # v1: every bit used
                assert bits == set(range(64)), f"{message.name} leaves bits unused"
    assert by_name["CONTACT_A"].cycle_time == by_name["CONTACT_B"].cycle_time
    assert by_name["STATUS"].cycle_time == 1000
    shape = by_name["CONTACT_B"].get_signal_by_name("SHAPE")
    assert {int(k): str(v) for k, v in shape.choices.items()} == {
        int(c): c.name.lower() for c in ShapeCode}
    # the package loader (importlib.resources) gives the same database as the file
    assert [m.name for m in load_database().messages] == [m.name for m in db.messages]


def test_message_ids_and_split():
    assert message_ids(0) == {"CONTACT_A": 0x300, "CONTACT_B": 0x301, "STATUS": 0x302,
                              "CONTACT2": 0x303, "RELEASE": 0x304, "MOTION": 0x305}  # v2's two, v3's one
    assert message_ids(5) == {"CONTACT_A": 0x350, "CONTACT_B": 0x351, "STATUS": 0x352, "CONTACT2": 0x353,
                              "RELEASE": 0x354, "MOTION": 0x355}
    top = max_sensor_id()
    assert top == 79 and message_ids(top)["STATUS"] <= 0x7FF
    for sensor in (0, 1, 17, top):
        for name, frame_id in message_ids(sensor).items():
            assert split_id(frame_id) == (sensor, name)
    assert split_id(0x2FF) is None and split_id(0x306) is None and split_id(0x800) is None
    assert split_id(0x305) == (0, "MOTION")
    assert split_id(0x303) == (0, "CONTACT2") and split_id(0x314) == (1, "RELEASE")
    with pytest.raises(TransportError):
        message_ids(top + 1)
    with pytest.raises(TransportError):
        message_ids(-1)
    with pytest.raises(TransportError):
        message_ids(0, base_id=0x305)  # not a multiple of 0x10
    assert message_ids(2, base_id=0x100)["CONTACT_B"] == 0x121


# -- encoding ----------------------------------------------------------------------------------


def _check_contact(msg: ContactMessage, a: dict, b: dict) -> None:
    assert a["X"] == pytest.approx(msg.x_mm, abs=MM / 2 + 1e-9)
    assert a["Y"] == pytest.approx(msg.y_mm, abs=MM / 2 + 1e-9)
    assert a["MAJOR"] == pytest.approx(msg.major_mm, abs=MM / 2 + 1e-9)
    assert a["MINOR"] == pytest.approx(msg.minor_mm, abs=MM / 2 + 1e-9)
    assert a["CONFIDENCE"] == pytest.approx(msg.confidence, abs=CONF / 2 + 1e-9)
    assert b["ANGLE"] == pytest.approx(msg.angle_deg, abs=DEG / 2 + 1e-9)
    assert b["STRENGTH"] == pytest.approx(msg.strength, abs=0.005 + 1e-9)
    assert b["SHAPE"] == int(msg.shape)
    assert b["FLAGS"] == int(msg.flags)
    assert b["AGE"] == msg.age_us
    assert a["COUNTER"] == b["COUNTER"]


@settings(max_examples=200, deadline=None)
@given(
    x=st.floats(-40.96, 40.95), y=st.floats(-40.96, 40.95), major=st.floats(0, 81.91),
    minor=st.floats(0, 81.91), angle=st.floats(-90, 90), strength=st.floats(0, 655.35),
    shape=st.sampled_from(list(ShapeCode)), conf=st.floats(0, 1), flags=st.integers(0, 31),
    age=st.integers(0, 65535), counter=st.integers(0, 100),
)
def test_contact_roundtrip_within_resolution(x, y, major, minor, angle, strength, shape, conf, flags, age,
                                             counter):
    codec = CanCodec(sensor_id=1)
    msg = ContactMessage(sensor_id=1, flags=ContactFlags(flags), x_mm=x, y_mm=y, major_mm=major,
                         minor_mm=minor, angle_deg=angle, strength=strength, shape=shape, confidence=conf,
                         age_us=age)
    pa, pb = codec.contact_payloads(msg, counter)
    db = _db()
    a = db.decode_message("CONTACT_A", pa)
    b = db.decode_message("CONTACT_B", pb, decode_choices=False)
    _check_contact(msg, a, b)
    assert a["COUNTER"] == counter % 16


def test_contact_saturates_instead_of_raising():
    codec = CanCodec()
    db = _db()
    msg = ContactMessage(flags=ContactFlags(0xFF), x_mm=1e6, y_mm=-1e6, major_mm=500.0, minor_mm=-3.0,
                         angle_deg=float("nan"), strength=1e9, shape=ShapeCode.UNKNOWN, confidence=7.0,
                         age_us=10**9)
    pa, pb = codec.contact_payloads(msg, 99)
    a, b = db.decode_message("CONTACT_A", pa), db.decode_message("CONTACT_B", pb, decode_choices=False)
    assert (a["X"], a["Y"], a["MAJOR"], a["MINOR"], a["CONFIDENCE"]) == pytest.approx(
        (40.95, -40.96, 81.91, 0.0, 1.0))
    assert b["ANGLE"] == 0.0  # NaN -> 0
    assert b["STRENGTH"] == pytest.approx(655.35)
    assert b["SHAPE"] == 255 and b["FLAGS"] == 0x1F and b["AGE"] == 65535
    assert a["COUNTER"] == b["COUNTER"] == 99 % 16

    msg = ContactMessage(x_mm=float("inf"), y_mm=float("-inf"), major_mm=float("nan"), strength=-5.0,
                         confidence=-1.0, age_us=-20, angle_deg=135.0)
    pa, pb = codec.contact_payloads(msg, 0)
    a, b = db.decode_message("CONTACT_A", pa), db.decode_message("CONTACT_B", pb, decode_choices=False)
    assert (a["X"], a["Y"], a["MAJOR"], a["CONFIDENCE"]) == pytest.approx((40.95, -40.96, 0.0, 0.0))
    assert b["STRENGTH"] == 0.0 and b["AGE"] == 0
    assert b["ANGLE"] == pytest.approx(-45.0)  # an axis at 135° is the axis at -45° (as on serial)

    pa, pb = codec.contact_payloads(ContactMessage(angle_deg=90.0, shape=42), 0)  # type: ignore[arg-type]
    b = db.decode_message("CONTACT_B", pb, decode_choices=False)
    assert b["ANGLE"] == pytest.approx(90.0) and b["SHAPE"] == 255  # unknown codes -> UNKNOWN


def test_rounding_matches_serial_protocol():
    from optitac_edge.io.protocol import wire

    codec = CanCodec()
    db = _db()
    values = [0.0, 0.005, 0.015, 0.125, -0.125, -0.005, 1.2345, -12.3449, 40.95, -40.95, 40.944999]
    for v in values:
        msg = ContactMessage(x_mm=v, y_mm=-v, major_mm=abs(v), minor_mm=abs(v) / 2, angle_deg=v * 2,
                             strength=abs(v) * 3, confidence=abs(v) / 41, age_us=int(abs(v) * 1000))
        pa, pb = codec.contact_payloads(msg, 0)
        a = db.decode_message("CONTACT_A", pa, scaling=False)
        b = db.decode_message("CONTACT_B", pb, scaling=False, decode_choices=False)
        serial = wire.CONTACT.unpack(wire.contact_payload(msg))
        # sensor_id, flags, x, y, major, minor, angle, strength, shape, confidence, age_us
        assert (a["X"], a["Y"], a["MAJOR"], a["MINOR"]) == serial[2:6], v
        assert (b["ANGLE"], b["STRENGTH"], b["SHAPE"], a["CONFIDENCE"], b["AGE"]) == serial[6:11], v
        assert b["FLAGS"] == serial[1]


def test_status_encoding():
    codec = CanCodec()
    db = _db()
    msg = StatusMessage(fps_x10=598, frames_dropped=300, camera_errors=17, link_errors=255,
                        cpu_temp_c_x10=523,
                        calibration_id=0xD2B18A46, state=0b1011)
    s = db.decode_message("STATUS", codec.status_payload(msg, 21), decode_choices=False)
    assert s == {"CALIBRATION_ID": 0xD2B1, "FPS": pytest.approx(59.8), "STATE": 0b1011, "CPU_TEMP": 52,
                 "FRAMES_DROPPED": 300 % 256, "LINK_ERRORS": 255, "CAMERA_ERRORS": 17 % 16, "COUNTER": 5}
    unknown = db.decode_message("STATUS", codec.status_payload(StatusMessage(), 0))
    assert str(unknown["CPU_TEMP"]) == "unknown"
    hot_msg = StatusMessage(cpu_temp_c_x10=30000, fps_x10=10**6)
    hot = db.decode_message("STATUS", codec.status_payload(hot_msg, 0), decode_choices=False)
    assert hot["CPU_TEMP"] == 214 and hot["FPS"] == pytest.approx(409.5)
    cold = db.decode_message("STATUS", codec.status_payload(StatusMessage(cpu_temp_c_x10=-1000), 0),
                             decode_choices=False)
    assert cold["CPU_TEMP"] == -40


def test_custom_dbc_is_checked(tmp_path):
    text = DBC_PATH.read_text().replace(" SG_ AGE : 44|16@1+ (1,0) [0|65535] \"us\" MCU\n", "")
    bad = tmp_path / "bad.dbc"
    bad.write_text(text)
    with pytest.raises(TransportError, match="AGE"):
        CanCodec(dbc_path=bad)
    with pytest.raises(TransportError):
        CanCodec(dbc_path=tmp_path / "missing.dbc")
    good = tmp_path / "copy.dbc"
    good.write_text(DBC_PATH.read_text())
    custom = CanCodec(dbc_path=good).contact_payloads(_contact(), 1)
    assert custom == CanCodec().contact_payloads(_contact(), 1)


# -- the transport on the virtual bus ----------------------------------------------------------


def test_contacts_and_status_over_virtual_bus(link):
    tx, rx = link
    assert tx.ids == {"CONTACT_A": 0x330, "CONTACT_B": 0x331, "STATUS": 0x332, "CONTACT2": 0x333, "RELEASE": 0x334,
                      "MOTION": 0x335}
    msgs = [_contact(x_mm=0.1 * i, angle_deg=-80 + 7.3 * i, age_us=100 * i) for i in range(5)]
    for m in msgs:
        send_message(tx, m)
    send_message(tx, StatusMessage(sensor_id=3, fps_x10=600, calibration_id=0x12345678, state=1))
    frames = _receive(rx, 11)
    db = _db()
    for i, m in enumerate(msgs):
        fa, fb = frames[2 * i], frames[2 * i + 1]
        assert (fa.arbitration_id, fb.arbitration_id) == (0x330, 0x331)
        assert not fa.is_extended_id and fa.dlc == fb.dlc == 8
        sa, na, a = decode_frame(fa.arbitration_id, fa.data)
        sb, nb, b = decode_frame(fb.arbitration_id, fb.data)
        assert (sa, na, sb, nb) == (3, "CONTACT_A", 3, "CONTACT_B")
        # the same through the DBC directly (ids of sensor 0 + 0x10*3)
        assert a == db.get_message_by_frame_id(fa.arbitration_id - 0x30).decode(fa.data)
        _check_contact(m, a, b)
        assert a["COUNTER"] == i
    sensor, name, status = decode_frame(frames[10].arbitration_id, frames[10].data)
    assert (sensor, name) == (3, "STATUS")
    assert status["FPS"] == pytest.approx(60.0) and status["CALIBRATION_ID"] == 0x1234
    assert status["STATE"] == 1
    assert status["COUNTER"] == 0
    assert tx.counters.sent == 11 and tx.counters.send_errors == 0
    assert rx.recv(0.01) is None


def test_counter_rolls_over_and_pairs(link):
    tx, rx = link
    n = 40
    for i in range(n):
        send_message(tx, _contact(age_us=i))
    frames = _receive(rx, 2 * n)
    counters = []
    for fa, fb in zip(frames[::2], frames[1::2]):
        _, _, a = decode_frame(fa.arbitration_id, fa.data)
        _, _, b = decode_frame(fb.arbitration_id, fb.data)
        assert a["COUNTER"] == b["COUNTER"]
        counters.append(a["COUNTER"])
    assert counters == [i % 16 for i in range(n)]


def test_registry_opens_can_transport():
    channel = _channel()
    with open_transport("can", channel=channel, interface="virtual", sensor_id=1) as t:
        assert isinstance(t, CanTransport) and t.ids["CONTACT_A"] == BASE_ID + 0x10
        assert t.connected
    assert t.closed and not t.connected


def test_bad_configuration_raises_transport_error():
    with pytest.raises(TransportError):
        CanTransport(channel="x", interface="no-such-interface")
    with pytest.raises(TransportError):
        CanTransport(channel="x", interface="virtual", sensor_id=200)


class _FlakyBus:
    """Wraps a real bus; ``fail`` holds exceptions the next sends raise."""

    def __init__(self, bus):
        self.bus = bus
        self.fail: list[BaseException] = []
        self.attempts = 0
        self.shutdowns = 0

    def send(self, msg, timeout=None):
        self.attempts += 1
        assert timeout == 0
        if self.fail:
            raise self.fail.pop(0)
        self.bus.send(msg, timeout)

    def shutdown(self):
        self.shutdowns += 1
        self.bus.shutdown()


@pytest.mark.parametrize("exc", [
    can.CanOperationError("Failed to transmit: No buffer space available", errno.ENOBUFS),
    OSError(errno.ENOBUFS, "No buffer space available"),
    can.CanOperationError("Transmit buffer full"),
    can.CanError("bus error"),
])
def test_send_errors_are_counted_and_dropped(link, exc):
    tx, rx = link
    flaky = _FlakyBus(tx._bus)
    tx._bus = flaky
    flaky.fail = [exc]
    send_message(tx, _contact())  # A fails: B is not attempted, both counted
    assert flaky.attempts == 1
    assert tx.counters.send_errors == 2 and tx.counters.sent == 0
    if "buffer" in str(exc) or getattr(exc, "errno", None) == errno.ENOBUFS:
        assert tx.stats.queue_full == 1
    else:
        assert tx.stats.other_errors == 1
    flaky.fail = [exc]
    send_message(tx, StatusMessage(sensor_id=3))
    assert tx.counters.send_errors == 3
    # later sends work; the counters show the gaps
    send_message(tx, _contact())
    send_message(tx, StatusMessage(sensor_id=3))
    frames = _receive(rx, 3)
    assert [f.arbitration_id for f in frames] == [0x330, 0x331, 0x332]
    assert decode_frame(frames[0].arbitration_id, frames[0].data)[2]["COUNTER"] == 1
    assert decode_frame(frames[2].arbitration_id, frames[2].data)[2]["COUNTER"] == 1
    assert tx.counters.sent == 3 and tx.connected and tx.stats.link_down == 0


def test_b_failure_counts_one(link):
    tx, rx = link
    flaky = _FlakyBus(tx._bus)
    tx._bus = flaky

    def fail_b(msg, timeout=None):
        if msg.arbitration_id == 0x331:
            raise OSError(errno.ENOBUFS, "No buffer space available")
        flaky.bus.send(msg, timeout)

    flaky.send = fail_b
    send_message(tx, _contact())
    assert tx.counters.sent == 1 and tx.counters.send_errors == 1
    assert [f.arbitration_id for f in _receive(rx, 1)] == [0x330]


def _wait(predicate, timeout: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


@pytest.mark.parametrize("exc", [
    can.CanOperationError("Failed to transmit: Network is down", errno.ENETDOWN),
    OSError(errno.ENODEV, "No such device"),
])
def test_interface_down_reopens_in_background(link, exc):
    tx, rx = link
    flaky = _FlakyBus(tx._bus)
    tx._bus = flaky
    flaky.fail = [exc]
    send_message(tx, StatusMessage(sensor_id=3))
    assert tx.stats.link_down == 1 and flaky.shutdowns == 1
    assert not tx.connected
    # frames offered while down are dropped and counted, without blocking
    t0 = time.perf_counter()
    send_message(tx, _contact())
    assert time.perf_counter() - t0 < 0.05
    assert tx.counters.send_errors == 3 and tx.stats.dropped_link_down >= 1
    assert _wait(lambda: tx.connected)
    assert tx.counters.reconnects == 1
    send_message(tx, _contact())
    frames = _receive(rx, 2)
    assert [f.arbitration_id for f in frames] == [0x330, 0x331]
    assert decode_frame(frames[0].arbitration_id, frames[0].data)[2]["COUNTER"] == 1


def test_persistent_failures_count_as_bus_off():
    channel = _channel()
    rx = can.Bus(channel=channel, interface="virtual")
    tx = CanTransport(channel=channel, interface="virtual", down_after=10, backoff_s=(0.01, 0.02))
    try:
        flaky = _FlakyBus(tx._bus)
        tx._bus = flaky
        flaky.fail = [OSError(errno.ENOBUFS, "No buffer space available")] * 10
        for _ in range(10):
            send_message(tx, StatusMessage())
        assert tx.stats.queue_full == 10 and tx.stats.link_down == 1
        assert _wait(lambda: tx.connected) and tx.counters.reconnects == 1
        send_message(tx, StatusMessage())
        assert _receive(rx, 1)[0].arbitration_id == 0x302
    finally:
        tx.close()
        rx.shutdown()


def test_reopen_retries_with_backoff(monkeypatch, link):
    tx, rx = link
    real_open = tx._open_bus
    attempts = []

    def failing_open():
        attempts.append(time.monotonic())
        if len(attempts) <= 3:
            raise can.CanInterfaceNotImplementedError("adapter unplugged")
        return real_open()

    monkeypatch.setattr(tx, "_open_bus", failing_open)
    flaky = _FlakyBus(tx._bus)
    tx._bus = flaky
    flaky.fail = [OSError(errno.ENODEV, "No such device")]
    send_message(tx, StatusMessage(sensor_id=3))
    assert _wait(lambda: tx.connected)
    assert tx.stats.open_failures == 3 and tx.counters.reconnects == 1 and len(attempts) == 4
    gaps = [b - a for a, b in itertools.pairwise(attempts)]
    assert gaps[-1] >= gaps[0] * 0.9  # waits grow (capped at 0.05 s here)
    send_message(tx, StatusMessage(sensor_id=3))
    assert _receive(rx, 1)[0].arbitration_id == 0x332


def test_close_is_idempotent_and_sends_after_close_are_dropped():
    channel = _channel()
    tx = CanTransport(channel=channel, interface="virtual", sensor_id=3)
    flaky = _FlakyBus(tx._bus)
    tx._bus = flaky
    tx.close()
    tx.close()
    assert flaky.shutdowns == 1 and tx.closed
    send_message(tx, _contact())
    send_message(tx, StatusMessage(sensor_id=3))
    assert tx.counters.sent == 0 and tx.counters.send_errors == 3


def test_close_while_reconnecting_stops_the_thread(link):
    tx, _ = link
    flaky = _FlakyBus(tx._bus)
    tx._bus = flaky
    tx._backoff = Backoff(10.0, 10.0)  # the thread would wait long
    flaky.fail = [OSError(errno.ENETDOWN, "Network is down")]
    send_message(tx, StatusMessage(sensor_id=3))
    thread = tx._reconnector
    assert thread is not None and thread.is_alive()
    t0 = time.perf_counter()
    tx.close()
    assert time.perf_counter() - t0 < 1.0 and not thread.is_alive() and not tx.connected


def test_fill_from_estimate_and_send(link):
    """ContactMessage.fill (as the service loop uses it) -> CAN -> the same numbers."""
    tx, rx = link

    class Est:
        contact = True
        x_mm, y_mm, major_mm, minor_mm, angle_deg = 2.345, -1.01, 4.4, 2.2, 33.333
        strength, shape, confidence = 15.5, "square", 0.66

    msg = ContactMessage(sensor_id=3).fill(Est(), t_ns=1_000_000, now_ns=3_500_000, calibrated=True, n_contacts=2)
    send_message(tx, msg)
    fa, fb = _receive(rx, 2)
    _, _, a = decode_frame(fa.arbitration_id, fa.data)
    _, _, b = decode_frame(fb.arbitration_id, fb.data, decode_choices=True)
    assert str(b["SHAPE"]) == "square"
    assert b["FLAGS"] == int(ContactFlags.CONTACT | ContactFlags.MORE_CONTACTS | ContactFlags.CALIBRATED)
    assert b["AGE"] == 2500
    assert a["X"] == pytest.approx(2.35) and b["ANGLE"] == pytest.approx(33.33)
    assert math.isclose(a["CONFIDENCE"], round(0.66 * 255) / 255)


def test_one_link_carries_every_sensor_of_a_board_on_its_own_ids_and_counters():
    """A board with several sensors shares one bus: each message goes out on its own sensor's ids with that
    sensor's counters; the link packs no message of a sensor it does not carry (refused when the sensor's
    packer is asked for: the board's sensors are the link's)."""
    channel = _channel()
    rx = can.Bus(channel=channel, interface="virtual")
    try:
        with CanTransport(channel=channel, interface="virtual", sensor_id=[1, 2]) as tx:
            for i in range(3):
                send_message(tx, _contact(sensor_id=1 + i % 2, age_us=i))
            send_message(tx, StatusMessage(sensor_id=2))
            with pytest.raises(TransportError, match="carries sensors 1, 2, not 5"):
                tx.packer(5)
            frames = _receive(rx, 7)
            got = []
            for f in frames:
                sensor, name, signals = decode_frame(f.arbitration_id, f.data)
                got.append((sensor, name, signals["COUNTER"]))
            assert got == [(1, "CONTACT_A", 0), (1, "CONTACT_B", 0), (2, "CONTACT_A", 0), (2, "CONTACT_B", 0),
                           (1, "CONTACT_A", 1), (1, "CONTACT_B", 1), (2, "STATUS", 0)]
            assert tx.counters.send_errors == 0 and rx.recv(0.01) is None
    finally:
        rx.shutdown()
    with pytest.raises(TransportError, match="distinct"):
        CanTransport(channel=channel, interface="virtual", sensor_id=[1, 1])


def test_a_contact2_part_that_fails_ends_its_message_and_each_part_not_sent_counts():
    """One send for every kind (the packet's frames in turn): when a frame fails, the frames after it are
    not attempted (a part without the rest is useless) and each is a send error, as CONTACT_B after a
    failed CONTACT_A always was; the CONTACT2 parts of the next frame go out whole."""
    from optitac_edge.io.protocol.messages import ContactV2Message

    tx2 = CanTransport(channel=_channel(), interface="virtual", sensor_id=3, protocol=2)
    try:
        flaky = _FlakyBus(tx2._bus)
        tx2._bus = flaky
        packer = tx2.packer(3)
        message = ContactV2Message(sensor_id=3, n_contacts=1, contact_id=7, x_mm=1.0)
        flaky.fail = [OSError(errno.ENOBUFS, "No buffer space available")]
        tx2.send(packer.contact2(message))
        assert flaky.attempts == 1 and tx2.counters.send_errors == 3 and tx2.counters.sent == 0
        tx2.send(packer.contact2(message))
        assert flaky.attempts == 4 and tx2.counters.sent == 3 and tx2.counters.send_errors == 3
    finally:
        tx2.close()


def test_every_transport_has_one_send() -> None:
    """Transports ship packed bytes (python-can's ``BusABC.send``): one send verb, whatever the message kind;
    packing is the link's packer's (the outbox calls it)."""
    from optitac_edge.io.transports import TRANSPORTS
    from optitac_edge.io.transports.base import Transport

    for name in TRANSPORTS:
        cls = TRANSPORTS.load(name)
        assert issubclass(cls, Transport)
        verbs = sorted(n for n in dir(cls) if n.startswith("send") and callable(getattr(cls, n)))
        assert verbs == ["send"], (name, verbs)
        assert callable(cls.packer)
