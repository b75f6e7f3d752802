"""Serial protocol v1 (optitac_edge.io.protocol): golden vectors, quantisation, decoder, commands."""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import pytest

from optitac_edge.io.protocol import wire
from optitac_edge.io.protocol.decoder import FrameDecoder
from optitac_edge.io.protocol.messages import (
    Command,
    CommandType,
    ContactFlags,
    ContactMessage,
    ResultCode,
    ShapeCode,
    StatusMessage,
)
from optitac_edge.io.protocol.wire import (
    CSV_HEADER,
    MsgType,
    ProtocolError,
    contact_csv_row,
    contact_fields,
    crc16,
    decode_ack,
    decode_contact,
    decode_status,
    encode_ack,
    encode_command,
    encode_contact,
    encode_frame,
    encode_status,
    is_sensor_type,
    parse_command,
)

ROOT = Path(__file__).resolve().parents[1]
VECTORS = ROOT / "tests" / "vectors"
VECTOR_FILES = ("contact.hex", "status.hex", "commands.hex", "ack.hex", "invalid.hex")


def _run(cmd, **kw):
    """subprocess.run without raising on a non-zero exit (the tests check returncode)."""
    return subprocess.run(cmd, check=False, **kw)


def load_vectors(name: str) -> list[tuple[str, str, dict[str, int], bytes]]:
    """(name, expect, keys, wire bytes) of every vector in a .hex file."""
    out, pending = [], None
    for line in (VECTORS / name).read_text().splitlines():
        if line.startswith("#"):
            m = re.match(r"#\s*([\w-]+):\s*(expect=.*?)(?: -- .*)?$", line)
            if m:
                fields = dict(tok.split("=", 1) for tok in m.group(2).split())
                expect = fields.pop("expect")
                pending = (m.group(1), expect, {k: int(v, 0) for k, v in fields.items()})
        elif line.strip() and pending:
            out.append((*pending, bytes.fromhex(line.strip())))
            pending = None
    return out


ALL_VECTORS = [v for f in VECTOR_FILES for v in load_vectors(f)]


def test_crc_check_value():
    assert crc16(b"123456789") == 0x29B1


def test_vectors_are_current():
    r = _run([sys.executable, str(ROOT / "tools" / "mcu" / "make_vectors.py"), "--check"],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_vector_inventory():
    names = {v[0] for v in ALL_VECTORS}
    assert len(ALL_VECTORS) == 40
    for needed in ("contact_none", "contact_negative", "contact_saturated", "status_nominal", "ping",
                   "tare", "stream_on", "threshold_300", "ack_ok", "bad_crc", "bad_cobs", "too_short",
                   "wrong_version", "overflow"):
        assert needed in names


@pytest.mark.parametrize("vec", ALL_VECTORS, ids=[v[0] for v in ALL_VECTORS])
def test_vector(vec):
    name, expect, keys, data = vec
    for chunking in ("whole", "bytes"):
        dec = FrameDecoder()
        if chunking == "whole":
            frames = dec.feed(data)
        else:
            frames = [f for b in data for f in dec.feed(b)]
        c = dec.counters
        if expect != "frame":
            assert frames == [] and c.frames == 0
            assert c.errors == 1 and getattr(c, expect) == 1, (name, c)
            continue
        assert len(frames) == 1 and c.errors == 0
        (f,) = frames
        assert (f.type, f.seq, f.t_us, len(f.payload)) == (keys["type"], keys["seq"], keys["t_us"],
                                                            keys["payload_len"])
        # re-encoding the decoded frame gives the same bytes
        assert encode_frame(f.type, f.seq, f.t_us, f.payload) == data
        if f.type == MsgType.CONTACT and len(f.payload) == 18:
            got = dict(zip(("sensor_id", "flags", "x", "y", "major", "minor", "angle", "strength",
                            "shape", "confidence", "age_us"), contact_fields(f.payload), strict=True))
            assert got == {k: keys[k] for k in got}
        elif f.type == MsgType.CONTACT:
            with pytest.raises(ProtocolError):
                decode_contact(f.payload)
        elif f.type == MsgType.STATUS:
            s = decode_status(f.payload, f.t_us)
            for k in ("sensor_id", "state", "fps_x10", "frames_dropped", "camera_errors",
                      "link_errors", "cpu_temp_c_x10", "calibration_id"):
                assert getattr(s, k) == keys[k], k
        elif f.type == MsgType.ACK:
            assert decode_ack(f.payload) == (keys["seq_acked"], keys["result"])
        else:
            parsed = parse_command(f.type, f.seq, f.payload)
            if keys["result"] == 0:
                assert isinstance(parsed, Command) and parsed.seq == f.seq
                if f.type == CommandType.STREAM:
                    assert (parsed.stream_on, parsed.rate_divider) == (bool(keys["on"]),
                                                                       keys["rate_divider"])
                if f.type == CommandType.SET_THRESHOLD:
                    assert parsed.threshold == keys["threshold"]
            else:
                assert parsed == (f.seq, ResultCode(keys["result"]))


def test_contact_physical_round_trip():
    m = ContactMessage(sensor_id=3, flags=ContactFlags.CONTACT | ContactFlags.CALIBRATED, t_us=99,
                       x_mm=-12.345, y_mm=7.891, major_mm=4.2, minor_mm=2.1, angle_deg=-45.678,
                       strength=123.456, shape=ShapeCode.ELLIPSE, confidence=0.73, age_us=3210)
    (f,) = FrameDecoder().feed(encode_contact(m, 11))
    d = decode_contact(f.payload, f.t_us)
    assert (f.type, f.seq, d.t_us, d.sensor_id, d.flags, d.shape, d.age_us) == (
        1, 11, 99, 3, m.flags, ShapeCode.ELLIPSE, 3210)
    for k, tol in (("x_mm", 0.005), ("y_mm", 0.005), ("major_mm", 0.005), ("minor_mm", 0.005),
                   ("angle_deg", 0.005), ("strength", 0.005), ("confidence", 0.5 / 255)):
        assert abs(getattr(d, k) - getattr(m, k)) <= tol + 1e-12, k


def test_contact_quantisation_edges():
    def fields(**kw):
        return contact_fields(wire.contact_payload(ContactMessage(**kw)))

    assert fields(x_mm=float("nan"), y_mm=float("inf"))[2:4] == (0, 32767)
    assert fields(x_mm=float("-inf"))[2] == -32768
    assert fields(x_mm=0.005)[2] == 1 and fields(x_mm=-0.005)[2] == -1  # half away from zero
    assert fields(angle_deg=95.0)[6] == -8500  # an axis: folded into [-90, 90]
    assert fields(angle_deg=-90.0)[6] == -9000 and fields(angle_deg=90.0)[6] == 9000
    assert fields(strength=-3.0)[7] == 0 and fields(strength=655.35)[7] == 65535
    assert fields(strength=1e9)[7] == 65535
    assert fields(confidence=1.0)[9] == 255 and fields(confidence=-1)[9] == 0
    assert fields(age_us=-5)[10] == 0 and fields(age_us=10**9)[10] == 65535
    assert fields(sensor_id=300)[0] == 255
    assert fields(shape=77)[8] == 255 and fields(shape=ShapeCode.SQUARE)[8] == 3
    assert fields(flags=0xFF)[1] == 0x1F  # reserved bits cleared


def test_contact_from_pipeline_estimate():
    class Est:
        contact = True
        x_mm, y_mm, major_mm, minor_mm, angle_deg = 1.0, -2.0, 3.0, 1.5, 10.0
        strength, shape, confidence = 42.0, "square", 0.9

    m = ContactMessage().fill(Est(), t_ns=5_000_000, now_ns=5_004_000, calibrated=True, n_contacts=2)
    (f,) = FrameDecoder().feed(encode_contact(m, 0))
    flags, x, y, *_rest, shape, _conf, age = contact_fields(f.payload)[1:]
    assert flags == 0x13 and (x, y) == (100, -200) and shape == 3 and age == 4 and f.t_us == 5000
    assert contact_csv_row(f).split(",")[:5] == ["0", "5000", "19", "100", "-200"]
    assert len(CSV_HEADER.split(",")) == len(contact_csv_row(f).split(","))


def test_status_round_trip():
    s = StatusMessage(sensor_id=2, t_us=1234, fps_x10=599, frames_dropped=7, camera_errors=1,
                      link_errors=3, cpu_temp_c_x10=-55, calibration_id=0x12345678, state=0b0011)
    (f,) = FrameDecoder().feed(encode_status(s, 9))
    assert f.type == MsgType.STATUS and decode_status(f.payload, f.t_us) == s


def test_ack_and_commands():
    (f,) = FrameDecoder().feed(encode_ack(513, ResultCode.OUT_OF_RANGE, 7, 1000))
    assert (f.type, f.seq, f.t_us) == (0x7F, 7, 1000)
    assert decode_ack(f.payload) == (513, 3)
    assert parse_command(0x10, 4, b"") == Command(CommandType.PING, 4)
    assert parse_command(0x11, 4, b"") == Command(CommandType.TARE, 4)
    cmd = parse_command(0x13, 5, b"\x2c\x01")
    assert cmd.threshold == 300 and cmd.threshold_relative == pytest.approx(0.03)
    assert parse_command(0x12, 6, b"\x00\x04") == Command(CommandType.STREAM, 6, False, 4)
    assert parse_command(0x55, 6, b"") == (6, ResultCode.UNKNOWN_COMMAND)
    assert parse_command(0x10, 6, b"\x00") == (6, ResultCode.BAD_LENGTH)
    assert parse_command(0x13, 6, b"\x00\x00") == (6, ResultCode.OUT_OF_RANGE)
    assert is_sensor_type(0x01) and is_sensor_type(0x7F) and not is_sensor_type(0x10)


def test_decoder_resync_and_empty_frames():
    good = encode_command(CommandType.PING, 1, 2)
    dec = FrameDecoder()
    # garbage before the first delimiter, empty frames, a frame split over calls
    frames = dec.feed(b"\x11\x22\x33") + dec.feed(b"\x00\x00\x00" + good[:5]) + dec.feed(good[5:] + good)
    assert [f.seq for f in frames] == [1, 1]
    assert dec.counters.frames == 2 and dec.counters.errors == 1 and dec.counters.cobs == 1


def test_decoder_overflow_is_bounded_and_counted_once():
    dec = FrameDecoder()
    assert dec.feed(b"\x01" * 10_000) == []
    assert dec.counters.overflow == 1 and len(dec._buf) == 0
    good = encode_command(CommandType.TARE, 3, 4)
    assert [f.seq for f in dec.feed(b"\x01" * 100 + b"\x00" + good)] == [3]
    assert dec.counters.overflow == 1 and dec.counters.errors == 1


def test_encode_frame_rejects_oversized_payload():
    with pytest.raises(ProtocolError):
        encode_frame(1, 0, 0, bytes(54))


def test_decode_contact_wrong_length():
    with pytest.raises(ProtocolError):
        decode_contact(b"\x00" * 17)
    with pytest.raises(ProtocolError):
        decode_status(b"")
    with pytest.raises(ProtocolError):
        decode_ack(b"\x00\x00")


def test_decoder_speed():
    """Not a benchmark: guards against an accidentally quadratic decoder."""
    import time

    m = ContactMessage(flags=ContactFlags.CONTACT, x_mm=1.0)
    stream = b"".join(encode_contact(m, i) for i in range(5000))
    dec = FrameDecoder()
    t0 = time.perf_counter()
    n = len(dec.feed(stream))
    assert n == 5000 and time.perf_counter() - t0 < 2.0
    assert math.isfinite(t0)
