"""Serial protocol v3 (docs/protocol.md §13): v2 and each contact's MOTION, only for an MCU that asks."""

from __future__ import annotations

import math
import threading

from fakes.list_camera import ListCamera
from hypothesis import given
from hypothesis import strategies as st

from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.frame_result import FrameResult
from optitac_edge.io.protocol.messages import (
    STATE_PROTOCOL_V2,
    STATE_PROTOCOL_V3,
    CommandType,
    MotionFlags,
    MotionMessage,
    ResultCode,
)
from optitac_edge.io.protocol.outbox import LinkState, SensorOutbox
from optitac_edge.io.protocol.wire import MsgType, decode_ack, decode_status, encode_command
from optitac_edge.io.protocol.wire_v2 import (
    MOTION,
    decode_contact2,
    decode_motion,
    encode_motion,
    motion_fields,
    motion_payload,
)


@given(vx=st.floats(-300, 300), vy=st.floats(-300, 300), vib=st.floats(0, 600), frame=st.integers(0, 10**6),
       slide=st.integers(0, 10**6), cid=st.integers(0, 255))
def test_motion_round_trips_within_its_lsb(vx, vy, vib, frame, slide, cid):
    m = MotionMessage(sensor_id=7, flags=0x1F, t_us=123, frame=frame, index=2, contact_id=cid, vx_mm_s=vx,
                      vy_mm_s=vy, slide_frame=slide, vibration=vib)
    d = decode_motion(motion_payload(m), 123)
    assert (d.sensor_id, d.flags, d.frame, d.index, d.contact_id) == (7, 0x1F, frame % 65536, 2, cid)
    assert abs(d.vx_mm_s - vx) <= 0.005 + 1e-9 and abs(d.vy_mm_s - vy) <= 0.005 + 1e-9
    assert d.slide_frame == slide % 65536 and abs(d.vibration - vib) <= 0.005 + 1e-9


def test_motion_saturates_masks_and_fits_the_64_byte_frame():
    f = motion_fields(motion_payload(MotionMessage(flags=0xFF, vx_mm_s=1e9, vy_mm_s=-math.inf, vibration=math.nan,
                                                   contact_id=999, index=-1)))
    assert f[1] == 0x3F and f[5] == 32767 and f[6] == -32768 and f[8] == 0 and f[4] == 255 and f[3] == 0
    assert MOTION.size == 14 and len(encode_motion(MotionMessage(), 1)) <= 65  # 26 bytes on the wire


def test_a_motion_says_what_its_contact_and_frame_know():
    touch = ContactEstimate(contact=True, contact_id=3, touch_frame=9)  # velocity NaN: just touched
    m = MotionMessage().fill(touch, 0, 9, 9_000_000, math.nan, False, False)
    assert m.flags == 0 and (m.vx_mm_s, m.vy_mm_s, m.vibration, m.contact_id, m.t_us) == (0, 0, 0, 3, 9000)
    slid = ContactEstimate(contact=True, contact_id=3, vx_mm_s=12.0, vy_mm_s=-1.0, sliding=True, slide_frame=40)
    m.fill(slid, 1, 40, 0, 2.5, True, True)
    assert m.flags == int(MotionFlags.VELOCITY | MotionFlags.SLIDING | MotionFlags.SLIDE_BEGAN
                          | MotionFlags.VIBRATION | MotionFlags.VIBRATING | MotionFlags.VIBRATION_BEGAN)
    assert (m.index, m.slide_frame, m.vx_mm_s, m.vibration) == (1, 40, 12.0, 2.5)
    assert m.fill(slid, 1, 41, 0, 1.0, False, False).flags == int(MotionFlags.VELOCITY | MotionFlags.SLIDING
                                                               | MotionFlags.VIBRATION)
    none = m.fill(ContactEstimate(), 0, 42, 0, 1.0, False, False)
    assert none.flags == int(MotionFlags.VIBRATION) and none.contact_id == 0 and none.slide_frame == 0


def _result(n: int) -> FrameResult:
    contacts = [ContactEstimate(contact=k < n, contact_id=k + 1, touch_frame=1, vx_mm_s=float(k), vy_mm_s=0.0)
                for k in range(4)]
    result = FrameResult(contacts, [(0, -1)] * 4, frame=5)
    result.n_contacts, result.vibration = n, 1.1
    return result


def test_only_v3_sends_motion_each_after_its_contact2():
    outbox = SensorOutbox(2)
    for protocol, kinds in ((1, ["ContactMessage"]), (2, ["ContactV2Message"] * 2),
                            (3, ["ContactV2Message", "MotionMessage"] * 2)):
        out = outbox.messages(_result(2), LinkState(protocol=protocol), True, 10)
        assert [type(m).__name__ for m in out] == kinds
    out = outbox.messages(_result(2), LinkState(protocol=3), True, 10)
    for c2, motion in zip(out[::2], out[1::2]):
        assert (motion.frame, motion.index, motion.contact_id) == (c2.frame, c2.index, c2.contact_id)
    out = outbox.messages(_result(0), LinkState(protocol=3), True, 10)
    assert [type(m).__name__ for m in out] == ["ContactV2Message", "MotionMessage"] and out[1].contact_id == 0


def test_a_slide_reaches_a_v3_mcu_and_a_v2_mcu_never_sees_motion(bundle_path):
    """The service over a serial line: a press held then slid at 20 mm/s. An MCU that asks for v3 gets a MOTION
    after every CONTACT2, the slide's onset flagged once and its velocity; STATUS says v2 and v3. One that asks
    for v2 gets the same CONTACT2s and no MOTION."""
    from fakes.mcu import FakeMcu
    from fakes.slide import slide_frames

    from optitac_edge.config import load_board_config
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.transports.serial import SerialTransport
    from optitac_edge.service.loop import Service

    bundle = load_bundle(bundle_path)
    frames = slide_frames(bundle.baseline_frames + 20, 60, 60, 20.0, seed=8)
    got = {}
    for version in (2, 3):
        mcu = FakeMcu()
        config = load_board_config("sim", env={}, overrides={"link.transport": "serial",
                                                             "link.serial_url": mcu.path})
        try:
            # the MCU reads only after the run: every message waits in the queue (a busy machine's writer thread
            # falls behind; 256 dropped the oldest and the two runs' counts differed, issue 38 item 25)
            with SerialTransport(mcu.path, queue_size=4096) as link:
                mcu.write(encode_command(CommandType.SET_PROTOCOL, 5, 0, version=version))
                assert mcu.read_until(lambda fr: len(fr) >= 1)
                Service(config, bundle, ListCamera(frames), link).run(threading.Event())  # 240 fps
                assert link.wait_idle(10.0) and link.stats()["dropped"] == 0
                got[version] = mcu.read_until(lambda fr: fr and fr[-1].type == MsgType.STATUS, timeout=5)
        finally:
            mcu.close()
        ack = decode_ack(got[version][0].payload)
        assert (ack.seq_acked, ack.result) == (5, ResultCode.OK)
    assert not any(f.type == MsgType.MOTION for f in got[2])
    frames3 = [f for f in got[3] if f.type in (MsgType.CONTACT2, MsgType.MOTION)]
    assert frames3 and all(a.type == MsgType.CONTACT2 and b.type == MsgType.MOTION
                           for a, b in zip(frames3[::2], frames3[1::2]))
    pairs = [(decode_contact2(a.payload), decode_motion(b.payload)) for a, b in zip(frames3[::2], frames3[1::2])]
    assert all((c.frame, c.index, c.contact_id) == (m.frame, m.index, m.contact_id) for c, m in pairs)
    began = [m for _, m in pairs if m.flags & MotionFlags.SLIDE_BEGAN]
    assert len(began) == 1 and began[0].slide_frame == began[0].frame
    sliding = [m for _, m in pairs if m.flags & MotionFlags.SLIDING]
    assert sliding and abs(sliding[-1].vx_mm_s - 20.0) < 3.0
    assert len([f for f in got[2] if f.type == MsgType.CONTACT2]) == len(pairs)
    status = decode_status([f for f in got[3] if f.type == MsgType.STATUS][-1].payload)
    assert status.state & STATE_PROTOCOL_V2 and status.state & STATE_PROTOCOL_V3
    status2 = decode_status([f for f in got[2] if f.type == MsgType.STATUS][-1].payload)
    assert status2.state & STATE_PROTOCOL_V2 and not status2.state & STATE_PROTOCOL_V3
