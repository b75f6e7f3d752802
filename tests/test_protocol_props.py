"""Property tests of the serial protocol v1 codec (hypothesis)."""

from __future__ import annotations

import math

from hypothesis import given, settings
from hypothesis import strategies as st

from optitac_edge.io.protocol import wire
from optitac_edge.io.protocol.decoder import FrameDecoder
from optitac_edge.io.protocol.messages import ContactFlags, ContactMessage, ShapeCode, StatusMessage
from optitac_edge.io.protocol.wire import (
    contact_fields,
    decode_contact,
    decode_status,
    encode_contact,
    encode_frame,
    encode_status,
    parse_command,
)

i16 = st.integers(-32768, 32767)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)


@settings(max_examples=300, deadline=None)
@given(sid=st.integers(0, 255), flags=st.integers(0, 0x1F), x=i16, y=i16, major=u16, minor=u16,
       angle=st.integers(-9000, 9000), strength=u16, shape=st.sampled_from(list(ShapeCode)),
       conf=st.integers(0, 255), age=u16, seq=u16, t_us=u32)
def test_contact_wire_values_round_trip_exactly(sid, flags, x, y, major, minor, angle, strength, shape,
                                                 conf, age, seq, t_us):
    """Every representable wire value survives physical -> wire -> physical -> wire."""
    m = ContactMessage(sensor_id=sid, flags=ContactFlags(flags), t_us=t_us, x_mm=x * 0.01,
                       y_mm=y * 0.01, major_mm=major * 0.01, minor_mm=minor * 0.01,
                       angle_deg=angle * 0.01, strength=strength * 0.01, shape=shape,
                       confidence=conf / 255, age_us=age)
    (f,) = FrameDecoder().feed(encode_contact(m, seq))
    assert (f.type, f.seq, f.t_us) == (1, seq, t_us)
    assert contact_fields(f.payload) == (sid, flags, x, y, major, minor, angle, strength, int(shape),
                                         conf, age)
    d = decode_contact(f.payload, f.t_us)
    assert encode_contact(d, seq) == encode_contact(m, seq)


finite = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=300, deadline=None)
@given(x=finite, y=finite, major=finite, minor=finite, angle=finite, strength=finite, conf=finite,
       age=st.integers(-10**12, 10**12), t_us=st.integers(0, 2**64), seq=st.integers(0, 2**20))
def test_contact_any_float_quantises_within_resolution(x, y, major, minor, angle, strength, conf, age,
                                                        t_us, seq):
    m = ContactMessage(flags=ContactFlags.CONTACT, t_us=t_us, x_mm=x, y_mm=y, major_mm=major,
                       minor_mm=minor, angle_deg=angle, strength=strength, confidence=conf, age_us=age)
    (f,) = FrameDecoder().feed(encode_contact(m, seq))
    assert f.seq == seq & 0xFFFF and f.t_us == t_us & 0xFFFFFFFF
    d = decode_contact(f.payload)

    def near(value, got, lsb, lo, hi):
        if math.isnan(value):
            return got == 0
        clamped = min(max(value, lo * lsb), hi * lsb)
        return abs(got - clamped) <= lsb / 2 + 1e-9 * max(1.0, abs(clamped))

    assert near(x, d.x_mm, 0.01, -32768, 32767) and near(y, d.y_mm, 0.01, -32768, 32767)
    assert near(major, d.major_mm, 0.01, 0, 65535) and near(minor, d.minor_mm, 0.01, 0, 65535)
    assert near(strength, d.strength, 0.01, 0, 65535)
    assert near(conf, d.confidence, 1 / 255, 0, 255)
    assert -90.0 <= d.angle_deg <= 90.0
    assert d.age_us == min(max(age, 0), 65535)


@settings(max_examples=200, deadline=None)
@given(fps=u16, dropped=u32, cam=u32, link=u32, temp=i16, cal=u32, state=st.integers(0, 15),
       sid=st.integers(0, 255), seq=u16, t_us=u32)
def test_status_round_trip(fps, dropped, cam, link, temp, cal, state, sid, seq, t_us):
    s = StatusMessage(sensor_id=sid, t_us=t_us, fps_x10=fps, frames_dropped=dropped, camera_errors=cam,
                      link_errors=link, cpu_temp_c_x10=temp, calibration_id=cal, state=state)
    (f,) = FrameDecoder().feed(encode_status(s, seq))
    assert decode_status(f.payload, f.t_us) == s and f.seq == seq


@settings(max_examples=500, deadline=None)
@given(data=st.binary(max_size=400), cuts=st.lists(st.integers(0, 400), max_size=8))
def test_arbitrary_bytes_never_raise_and_chunking_does_not_matter(data, cuts):
    whole = FrameDecoder()
    frames = whole.feed(data)
    pieces, last = [], 0
    for c in sorted({min(c, len(data)) for c in cuts}):
        pieces.append(data[last:c])
        last = c
    pieces.append(data[last:])
    chunked = FrameDecoder()
    got = [f for p in pieces for f in chunked.feed(p)]
    assert got == frames and chunked.counters == whole.counters
    for f in frames:  # whatever is accepted is genuinely valid
        body = wire.HEADER.pack(1, f.type, f.seq, f.t_us) + f.payload
        assert encode_frame(f.type, f.seq, f.t_us, f.payload) == wire.cobs.encode(
            body + wire.CRC.pack(wire.crc16(body))) + b"\x00"
        parse_command(f.type, f.seq, f.payload)  # never raises either


@settings(max_examples=300, deadline=None)
@given(t=st.integers(0, 255), seq=u16, t_us=u32, payload=st.binary(max_size=wire.MAX_PAYLOAD))
def test_any_frame_round_trips(t, seq, t_us, payload):
    data = encode_frame(t, seq, t_us, payload)
    assert len(data) <= wire.MAX_ENCODED + 1
    dec = FrameDecoder()
    assert dec.feed(data) == [wire.Frame(t, seq, t_us, payload)] and dec.counters.errors == 0
    result = parse_command(t, seq, payload)
    assert result is not None


def _quantise_by_the_spec(value: float, lsb: float, lo: int, hi: int) -> int:
    """The wire's rule written out plainly: NaN 0, infinities saturate, else value/lsb rounded half away from
    zero and saturated."""
    import math

    if math.isnan(value):
        return 0
    if math.isinf(value):
        return hi if value > 0 else lo
    x = value / lsb
    n = math.floor(abs(x) + 0.5) * (1 if x >= 0 else -1) if math.isfinite(x) else (hi if x > 0 else lo)
    return max(lo, min(hi, n))


@given(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-10**6, 10**6).map(lambda k: k / 200)),
       st.sampled_from([(0.01, -32768, 32767), (0.01, 0, 65535), (1 / 255, 0, 255), (0.01, -9000, 9000)]))
def test_quantise_is_the_wires_rule(value, scale) -> None:
    """wire.quantise (written for speed: it runs for every field of every message) against the rule stated
    plainly, ties and saturation included."""
    from optitac_edge.io.protocol.wire import quantise

    lsb, lo, hi = scale
    assert quantise(value, lsb, lo, hi) == _quantise_by_the_spec(value, lsb, lo, hi)
