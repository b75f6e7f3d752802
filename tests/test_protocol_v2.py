"""Serial protocol v2 (docs/protocol.md §8): CONTACT2 and RELEASE, the SET_PROTOCOL switch, the service."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

# -- the messages ------------------------------------------------------------------------------
from fakes.list_camera import ListCamera
from hypothesis import given
from hypothesis import strategies as st

from optitac_edge.core.contact import ContactEstimate
from optitac_edge.io.protocol.announce import ContactAnnouncer
from optitac_edge.io.protocol.messages import (
    STATE_PROTOCOL_V2,
    Command,
    CommandType,
    ContactV2Flags,
    ContactV2Message,
    ReleaseMessage,
    ResultCode,
    ShapeCode,
)
from optitac_edge.io.protocol.wire import MsgType, decode_ack, decode_status, encode_command, parse_command
from optitac_edge.io.protocol.wire_v2 import (
    CONTACT2,
    contact2_fields,
    contact2_payload,
    decode_contact2,
    decode_release,
    encode_contact2,
    release_payload,
)


@given(x=st.floats(-300, 300), y=st.floats(-300, 300), depth=st.floats(0, 60), force=st.floats(0, 60),
       frame=st.integers(0, 10**6), cid=st.integers(0, 255), conf=st.floats(0, 1))
def test_contact2_round_trips_within_its_lsb(x, y, depth, force, frame, cid, conf):
    m = ContactV2Message(sensor_id=7, flags=0x35, t_us=123, frame=frame, index=1, n_contacts=2, contact_id=cid,
                         x_mm=x, y_mm=y, major_mm=4.2, minor_mm=3.1, angle_deg=-45.5, strength=12.34,
                         depth_mm=depth, force_n=force, shape=ShapeCode.CIRCLE, confidence=conf, age_us=900)
    d = decode_contact2(contact2_payload(m), 123)
    assert (d.sensor_id, d.flags, d.frame, d.index, d.n_contacts, d.contact_id) == (7, 0x35, frame % 65536, 1, 2, cid)
    assert abs(d.x_mm - x) <= 0.005 + 1e-9 and abs(d.y_mm - y) <= 0.005 + 1e-9
    assert abs(d.depth_mm - depth) <= 0.0005 + 1e-9 and abs(d.force_n - force) <= 0.0005 + 1e-9
    assert abs(d.confidence - conf) <= 0.5 / 255 + 1e-9 and d.shape == ShapeCode.CIRCLE and d.age_us == 900


def test_contact2_saturates_masks_and_fits_the_64_byte_frame():
    m = ContactV2Message(flags=0xFF, depth_mm=1e9, force_n=-3.0, x_mm=math.inf, y_mm=math.nan, contact_id=999,
                         n_contacts=-1, age_us=10**9)
    f = contact2_fields(contact2_payload(m))
    assert f[1] == 0x7F and f[13] == 65535 and f[14] == 0 and f[7] == 32767 and f[8] == 0
    assert f[5] == 255 and f[4] == 0 and f[16] == 0 and f[17] == 65535
    assert CONTACT2.size == 28 and len(encode_contact2(m, 1)) <= 65  # + COBS and the delimiter: 40 bytes
    r = decode_release(release_payload(ReleaseMessage(sensor_id=2, contact_id=9, frame=70000, touch_frame=5)))
    assert (r.sensor_id, r.contact_id, r.frame, r.touch_frame) == (2, 9, 70000 % 65536, 5)


def test_contact2_fill_carries_every_field_and_flags_depth_and_force_only_when_calibrated():
    est = ContactEstimate(contact=True, x_mm=1.0, y_mm=2.0, major_mm=5.0, minor_mm=4.0, angle_deg=10.0,
                          strength=8.0, shape="circle", confidence=0.9, depth_mm=1.5,
                          force_n=math.nan, contact_id=3, touch_frame=40)
    m = ContactV2Message(sensor_id=1).fill(est, 1, 40, 2, 5_000_000, 5_400_000, calibrated=True)
    assert m.flags == ContactV2Flags.CONTACT | ContactV2Flags.CALIBRATED | ContactV2Flags.TOUCH | ContactV2Flags.DEPTH
    assert (m.frame, m.index, m.n_contacts, m.contact_id, m.depth_mm, m.force_n, m.age_us) == (40, 1, 2, 3, 1.5, 0.0, 400)
    assert not ContactV2Message().fill(est, 0, 41, 2, 0, 0, calibrated=False).flags & ContactV2Flags.TOUCH
    none = ContactV2Message().fill(ContactEstimate(), 0, 42, 0, 0, 0, calibrated=False)
    assert (none.flags, none.n_contacts, none.contact_id, none.shape) == (0, 0, 0, ShapeCode.NONE)


@pytest.mark.parametrize("payload_version, expect", [(1, None), (2, None), (3, None), (0, ResultCode.OUT_OF_RANGE),
                                                     (4, ResultCode.OUT_OF_RANGE)])
def test_set_protocol_is_validated(payload_version, expect):
    got = parse_command(CommandType.SET_PROTOCOL, 9, bytes([payload_version]))
    if expect is None:
        assert got == Command(CommandType.SET_PROTOCOL, 9, version=payload_version)
    else:
        assert got == (9, expect)
    assert parse_command(CommandType.SET_PROTOCOL, 9, b"") == (9, ResultCode.BAD_LENGTH)


# -- the announcer -------------------------------------------------------------------------------


def test_touches_and_releases_are_relative_to_the_frames_sent():
    """The tracker's releases between sent frames go out with the next sent frame; an id handed out again is
    a new touch (the frames come from a tracker, as the pipeline's)."""
    from optitac_edge.core.frame_result import FrameResult

    released: list[tuple[int, int]] = [(0, -1)] * 8
    contacts = [ContactEstimate() for _ in range(4)]
    result = FrameResult(contacts, released)

    def frame(now: list[tuple[int, int]], gone: list[tuple[int, int]] = ()) -> FrameResult:
        for c, (cid, touch) in zip(contacts, now):
            c.contact, c.contact_id, c.touch_frame = True, cid, touch
        released[:len(gone)] = gone
        result.n_contacts, result.n_released = len(now), len(gone)
        return result

    a = ContactAnnouncer()

    def sent(r: FrameResult) -> list[tuple[int, int]]:
        a.observe(r)
        return a.announce(r)

    assert sent(frame([(1, 10)])) == [] and a.touched == [True]
    assert sent(frame([(1, 10), (2, 12)])) == [] and a.touched == [False, True]
    # frames 13-20 are not sent (rate divider): contact 2 goes, 3 comes and goes, 4 comes; 1 stays
    for now, gone in (([(1, 10)], [(2, 12)]), ([(1, 10), (3, 15)], []), ([(1, 10)], [(3, 15)]),
                      ([(1, 10), (4, 18)], [])):
        a.observe(frame(now, gone))
    assert a.announce(frame([(1, 10), (4, 18)])) == [(2, 12)] and a.touched == [False, True]  # never told of 3
    assert sent(frame([], [(1, 10), (4, 18)])) == [(1, 10), (4, 18)]
    assert sent(frame([(1, 30)])) == [] and a.touched == [True]  # id 1 handed out again: a touch
    assert sent(frame([(1, 40)], [(1, 30)])) == [(1, 30)] and a.touched == [True]  # and again
    a.reset()
    assert sent(frame([(1, 40)])) == [] and a.touched == [True]


# -- the service over a serial line ------------------------------------------------------------


def test_two_presses_reach_the_mcu_in_every_frame_with_stable_ids_after_it_asks_for_v2(bundle_path):
    """Issue 16: after SET_PROTOCOL 2 every contact of every frame is on the wire as CONTACT2 with a stable id
    through 100 frames; the release of both is announced; STATUS says v2."""
    from fakes.mcu import FakeMcu

    from optitac_edge.config import load_board_config
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.transports.serial import SerialTransport
    from optitac_edge.service.loop import Service
    from optitac_edge.sim.multi_press import multi_press_frames

    bundle = load_bundle(bundle_path)
    rest = bundle.baseline_frames
    frames = multi_press_frames(2, 100, rest, layout=bundle.layout, seed=5)
    frames += frames[:3]  # contact-free again: both released
    mcu = FakeMcu()
    config = load_board_config("sim", env={}, overrides={"link.transport": "serial", "link.serial_url": mcu.path,
                                                         "sensor.id": 4})
    try:
        with SerialTransport(mcu.path, queue_size=64) as link:
            mcu.write(encode_command(CommandType.SET_PROTOCOL, 77, 0, version=2))
            assert mcu.read_until(lambda fr: len(fr) >= 1)  # the ACK: the command was taken
            service = Service(config, bundle, ListCamera(frames), link)
            service.run(threading.Event())
            assert link.wait_idle(3.0)
            n_expected = 1 + 1 + rest - 1 + 2 * 100 + 2 + 3 + 1  # ACK, CONTACT, rest, presses, releases, end, STATUS
            # everything is written (wait_idle); the last frame is the STATUS sent at the end of the run
            got = mcu.read_until(lambda fr: len(fr) >= n_expected and fr[-1].type == MsgType.STATUS, timeout=5)
    finally:
        mcu.close()
    ack = decode_ack(got[0].payload)
    assert got[0].type == MsgType.ACK and (ack.seq_acked, ack.result) == (77, ResultCode.OK)
    assert got[1].type == MsgType.CONTACT  # frame 0 went out before the loop read the command: v1
    v2 = [decode_contact2(f.payload, f.t_us) for f in got if f.type == MsgType.CONTACT2]
    by_frame: dict[int, list[ContactV2Message]] = {}
    for m in v2:
        by_frame.setdefault(m.frame, []).append(m)
    pressed = [by_frame[k] for k in sorted(by_frame) if by_frame[k][0].n_contacts]
    assert len(pressed) == 100 and all(len(ms) == 2 and [m.index for m in ms] == [0, 1] for ms in pressed)
    ids = {m.contact_id for m in pressed[0]}
    assert len(ids) == 2 and all({m.contact_id for m in ms} == ids for ms in pressed)
    assert all(m.flags & ContactV2Flags.TOUCH for m in pressed[0])
    assert not any(m.flags & ContactV2Flags.TOUCH for ms in pressed[1:] for m in ms)
    assert all(m.sensor_id == 4 and m.depth_mm == 0 and not m.flags & ContactV2Flags.DEPTH for m in v2)
    releases = [decode_release(f.payload) for f in got if f.type == MsgType.RELEASE]
    assert sorted(r.contact_id for r in releases) == sorted(ids)
    assert all(r.touch_frame == pressed[0][0].frame for r in releases)
    status = [decode_status(f.payload) for f in got if f.type == MsgType.STATUS]
    assert status and status[-1].state & STATE_PROTOCOL_V2


def test_a_link_without_v2_ignores_set_protocol_2_and_counts_it(bundle_path):
    from optitac_edge.config import load_board_config
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.transports.base import NullTransport
    from optitac_edge.service.loop import Service

    class V1Only(NullTransport):
        protocols = (1,)

    bundle = load_bundle(bundle_path)
    frame = np.zeros((bundle.fibers.height, bundle.fibers.width), dtype=np.uint8)
    service = Service(load_board_config("sim", env={}), bundle, ListCamera([frame]), V1Only())
    service.handle(Command(CommandType.SET_PROTOCOL, 1, version=2))
    assert service.link.protocol == 1 and service.stats.protocol_refused == 1
    assert not service.status.message(0).state & STATE_PROTOCOL_V2
