"""The service on the network: the publishing thread (queue, drops, events) with the virtual publisher,
and `optitac-edge run --publish zenoh` received by a subscriber in another process."""

from __future__ import annotations

import csv
import json
import math
import re
import subprocess
import sys
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from fakes.net import free_port
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from optitac_edge.core.frame_result import FrameResult
from optitac_edge.errors import PublishError
from optitac_edge.io.protocol.messages import STATE_BASELINE_READY, STATE_STREAMING, StatusMessage
from optitac_edge.io.protocol.wire import MsgType
from optitac_edge.io.publishers import open_publisher
from optitac_edge.io.publishers.virtual import VirtualPublisher
from optitac_edge.io.ros2 import messages as msgs
from optitac_edge.service.network import NetworkOutput, NetworkSensor

ROOT = Path(__file__).resolve().parent.parent
SUBSCRIBER = ROOT / "examples" / "zenoh_subscriber.py"


@pytest.fixture(scope="module")
def store():
    ts = get_typestore(Stores.ROS2_JAZZY)
    for path in sorted((ROOT / "ros2" / "optitac_msgs" / "msg").glob("*.msg")):
        ts.register(get_types_from_msg(path.read_text(), f"optitac_msgs/msg/{path.stem}"))
    return ts


def sensor(sensor_id: int = 1, name: str = "thumb") -> NetworkSensor:
    n = 7
    return NetworkSensor(sensor_id, name, np.arange(n, dtype=np.float32), -np.arange(n, dtype=np.float32),
                         np.zeros(n, bool), "c0ffee")


def contact(cid: int, frame: int, touch_frame: int, x: float = 1.0) -> SimpleNamespace:
    return SimpleNamespace(contact_id=cid, touch_frame=touch_frame, x_mm=x, y_mm=-x, major_mm=3.0,
                           minor_mm=2.0, angle_deg=10.0, strength=5.0, depth_mm=math.nan, force_n=0.5,
                           shape="", confidence=math.nan, vx_mm_s=2.5 * cid, vy_mm_s=-1.0, sliding=cid == 2,
                           slide_frame=frame if cid == 2 else -1)


def frame_(index: int, *contacts: SimpleNamespace, t_ns: int = 0, released: tuple[tuple[int, int], ...] = (),
           calibrated: bool = True) -> FrameResult:
    """A frame's result as the pipeline gives it (the tracker's releases given)."""
    slots = [*contacts, *(contact(0, index, 0) for _ in range(4 - len(contacts)))]
    result = FrameResult(slots, [*released, *[(0, -1)] * 4], frame=index, t_ns=t_ns)  # type: ignore[arg-type]
    result.n_contacts, result.n_released, result.calibrated = len(contacts), len(released), calibrated
    return result


def test_every_contact_with_touch_and_release_events(store):
    pub = VirtualPublisher()
    with NetworkOutput(pub, [sensor()]) as net:
        frames = [frame_(0, t_ns=1000), frame_(1, contact(1, 1, 1), t_ns=1001),
                  frame_(2, contact(1, 2, 1), contact(2, 2, 2, x=5.0), t_ns=1002),
                  frame_(3, contact(2, 3, 2, x=5.0), t_ns=1003, released=((1, 1),)),
                  frame_(4, t_ns=1004, released=((2, 2),))]
        for result in frames:
            net.offer_frame(1, result, False)
    got = [store.deserialize_cdr(m.payload, msgs.CONTACTS) for m in pub.taken("/optitac/thumb/contacts")]
    assert [m.frame for m in got] == [0, 1, 2, 3, 4] and [m.t_ns for m in got] == [1000, 1001, 1002, 1003, 1004]
    assert [[c.id for c in m.contacts] for m in got] == [[], [1], [1, 2], [2], []]
    assert [[c.touch for c in m.contacts] for m in got] == [[], [True], [False, True], [False], []]
    assert [list(m.released) for m in got] == [[], [], [], [1], [2]]
    assert got[2].contacts[1].x_mm == 5.0 and math.isnan(got[2].contacts[1].depth_mm)
    assert got[2].contacts[1].force_n == 0.5 and got[0].header.frame_id == "optitac_thumb"


class StuckPublisher(VirtualPublisher):
    """A network that takes nothing until :attr:`release` is set (a subscriber gone, a full link)."""

    def __init__(self) -> None:
        super().__init__()
        self.release = threading.Event()
        self.waiting = threading.Event()

    def publish(self, handle: int, payload: bytes, source_ns: int) -> None:
        self.waiting.set()
        self.release.wait()
        super().publish(handle, payload, source_ns)


def test_a_release_in_frames_the_queue_dropped_comes_with_the_next_frame_published(store):
    """The tracker releases a contact once, in its frame; when the queue drops that frame, the next one
    published releases it (a subscriber never holds a contact that is gone)."""
    pub = StuckPublisher()
    net = NetworkOutput(pub, [sensor(3)], queue=2)
    net.offer_frame(3, frame_(0, contact(7, 0, 0)), False)
    assert pub.waiting.wait(10)  # frame 0 is being published: taken off the queue
    net.offer_frame(3, frame_(1, released=((7, 0),)), False)  # dropped: the queue holds 2
    for k in (2, 3):
        net.offer_frame(3, frame_(k), False)
    pub.release.set()
    net.close()
    got = [store.deserialize_cdr(m.payload, msgs.CONTACTS) for m in pub.taken()]
    assert [m.frame for m in got] == [0, 2, 3]
    assert [list(m.released) for m in got] == [[], [7], []]
    assert net.counters(3) == (3, 1)


def test_a_stuck_network_costs_the_frame_loop_nothing_and_every_drop_is_counted(store):
    pub = StuckPublisher()
    net = NetworkOutput(pub, [sensor(4)], queue=16)
    offered = 1000

    def loop() -> None:
        for k in range(offered):
            net.offer_frame(4, frame_(k, contact(1, k, 0), t_ns=k), False)

    t = threading.Thread(target=loop)
    t.start()
    t.join(30)
    assert not t.is_alive(), "the frame loop waited for the network"
    pub.release.set()
    net.close()
    published, dropped = net.counters(4)
    assert published == len(pub.taken()) and published + dropped == offered
    assert published <= 16 + 1 and dropped >= offered - 17
    frames = [store.deserialize_cdr(m.payload, msgs.CONTACTS).frame for m in pub.taken()]
    assert frames == sorted(frames) and frames[-1] == offered - 1  # the newest kept, the oldest dropped


class SlowStorage(StuckPublisher):
    """Each publish waits until released (an SD card's 0.4 s fsyncs); closing during one is the failure
    the real MCAP writer met ('write to closed file')."""

    def __init__(self) -> None:
        super().__init__()
        self.in_publish = 0
        self.closed_during_publish = False

    def publish(self, handle: int, payload: bytes, source_ns: int) -> None:
        self.in_publish += 1
        try:
            super().publish(handle, payload, source_ns)
        finally:
            self.in_publish -= 1

    def _close_internal(self) -> None:
        self.closed_during_publish = self.in_publish > 0
        super()._close_internal()


def test_closing_on_slow_storage_never_closes_the_publisher_under_a_write(store, monkeypatch):
    """run --mcap on an SD card: close() waited 5 s for the publishing thread, then closed the publisher while
    the thread still wrote (ValueError: write to closed file, exit 1, no summary). Now what is still queued
    after the wait is dropped and counted, and the publisher is closed once the write under way ends."""
    from optitac_edge.service import network

    monkeypatch.setattr(network, "CLOSE_WAIT_S", 0.05)
    pub = SlowStorage()
    net = NetworkOutput(pub, [sensor(5)], queue=64)
    for k in range(20):
        net.offer_frame(5, frame_(k, contact(1, k, 0), t_ns=k), False)
    assert pub.waiting.wait(10)  # the first is being written
    closing = threading.Thread(target=net.close)
    closing.start()
    closing.join(0.5)
    assert closing.is_alive()  # waits for the write under way...
    pub.release.set()
    closing.join(10)
    assert not closing.is_alive() and not pub.closed_during_publish  # ...and closes after it
    published, dropped = net.counters(5)
    assert published + dropped == 20 and dropped >= 1  # what was still queued is counted, not lost silently


def test_status_reports_the_sensor_and_the_publishers_counters(store):
    pub = VirtualPublisher()
    with NetworkOutput(pub, [sensor(2, "index-1")], signal_hz=10) as net:
        for k in range(3):
            net.offer_frame(2, frame_(k, t_ns=k * 50_000_000, calibrated=False), False,
                            signal=np.full(7, k, np.float32))
        status = StatusMessage(sensor_id=2, t_us=5, fps_x10=2400, frames_dropped=3, camera_errors=1,
                               link_errors=2, cpu_temp_c_x10=455, state=STATE_STREAMING | STATE_BASELINE_READY)
        net.offer_status(2, status, status.flags, frames=3, contacts=0, fps=240.0, protocol=2)
    (m,) = [store.deserialize_cdr(x.payload, msgs.STATUS) for x in pub.taken("/optitac/index_1/status")]
    assert (m.sensor_id, m.sensor_name, m.calibration_id, m.frames, m.frames_dropped, m.protocol) == \
        (2, "index-1", "c0ffee", 3, 3, 2)
    assert m.cpu_temp_c == pytest.approx(45.5) and m.streaming and m.baseline_ready and not m.camera_fault
    assert m.published == 5 and m.publish_dropped == 0  # 3 contacts and 2 signals (every 100 ms of 150)
    signals = [store.deserialize_cdr(x.payload, msgs.SIGNAL) for x in pub.taken("/optitac/index_1/signal")]
    assert [s.frame for s in signals] == [0, 2] and list(signals[1].signal) == [2.0] * 7
    assert list(signals[0].y_mm) == [-float(i) for i in range(7)]


@pytest.mark.parametrize(("names", "message"), [
    (["1st"], "sensor 1 '1st': its topic name '1st' is not a ROS 2 name"),
    (["a-b", "a.b"], "sensor 2 'a.b': its topics would be sensor 1 'a-b''s (a_b)"),
])
def test_sensor_names_that_make_no_topic_are_refused_naming_the_sensor(names, message):
    with pytest.raises(PublishError) as info:
        NetworkOutput(VirtualPublisher(), [sensor(k + 1, n) for k, n in enumerate(names)])
    assert message in str(info.value)


def test_an_unknown_publisher_is_refused_by_name():
    with pytest.raises(PublishError, match="unknown publisher 'mqtt'"):
        open_publisher("mqtt")


# -- the service on Zenoh, a subscriber in another process --------------------------------------


def _subscriber(port: int, out: Path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, str(SUBSCRIBER), "--listen", f"tcp/127.0.0.1:{port}", "--json",
                             "--idle", "1", "--seconds", "120"], stdout=out.open("w"), stderr=subprocess.PIPE,
                            text=True)
    assert "listening" in proc.stderr.readline()
    return proc


def _board(tmp_path: Path, name: str, camera: str, port: int, extra: str = "") -> Path:
    cfg = tmp_path / f"{name}.json5"
    cfg.write_text(f'{{ mode: "peer", connect: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, '
                   'scouting: { multicast: { enabled: false } } }')
    board = tmp_path / f"{name}.toml"
    board.write_text(f'{camera}\n[network]\n{extra}[publish.zenoh]\nconfig = "{cfg}"\n')
    return board


def _received(out: Path) -> list[dict]:
    return [json.loads(line) for line in out.read_text().splitlines() if line.strip()]


def test_the_example_subscriber_prints_contacts_and_status_in_its_default_mode(tmp_path, unseen_rec, bundle_path):
    """Its default (line) mode died at the first status message (len() of SensorStatus.contacts, a count),
    its thread with it, and the script still exited 0."""
    port = free_port()
    sub = subprocess.Popen([sys.executable, str(SUBSCRIBER), "--listen", f"tcp/127.0.0.1:{port}", "--idle", "1",
                            "--seconds", "120"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert sub.stderr is not None and "listening" in sub.stderr.readline()
    board = _board(tmp_path, "board", f'[sensor]\nname = "thumb"\n[camera]\nbackend = "recording"\n'
                   f'recording = "{unseen_rec}"\n[calibration]\nbundle = "{bundle_path}"\n[status]\nperiod_s = 0.5',
                   port)
    run = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "run", "--board", str(board), "--frames", "120"],
                         capture_output=True, text=True, timeout=120, check=False)
    assert run.returncode == 0, run.stderr[-2000:]
    out, err = sub.communicate(timeout=60)
    assert sub.returncode == 0 and "cannot decode" not in err, err
    lines = out.splitlines()
    contacts = [x for x in lines if x.startswith("/optitac/thumb/contacts optitac_msgs/msg/Contacts")]
    status = [x for x in lines if x.startswith("/optitac/thumb/status optitac_msgs/msg/SensorStatus")]
    assert len(contacts) == 120 and any(" 1 contact(s) [id " in x for x in contacts)
    assert status and re.search(r": \d+\.\d fps, \d+ frames, \d+ with contact$", status[-1])


def test_run_publishes_every_frame_equal_to_the_contacts_csv(tmp_path, unseen_rec, bundle_path):
    port = free_port()
    out = tmp_path / "received.jsonl"
    sub = _subscriber(port, out)
    board = _board(tmp_path, "board", f'[sensor]\nname = "thumb"\n[camera]\nbackend = "recording"\n'
                   f'recording = "{unseen_rec}"\n[calibration]\nbundle = "{bundle_path}"', port)
    run = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "run", "--board", str(board), "--frames", "300"],
                         capture_output=True, text=True, timeout=120, check=False)
    assert run.returncode == 0, run.stderr[-2000:]
    sub.wait(60)
    csv_path = tmp_path / "contacts.csv"
    replay = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "replay", str(unseen_rec), "--cal",
                             str(bundle_path), "-o", str(csv_path)], capture_output=True, text=True, check=False)
    assert replay.returncode == 0, replay.stderr
    rows = list(csv.DictReader(csv_path.open()))[:300]  # the frames the run processed
    got = [m for m in _received(out) if m["topic"] == "/optitac/thumb/contacts"]
    assert [m["message"]["frame"] for m in got] == list(range(300))
    assert re.search(r"sensor 0 'thumb': 30\d messages published, 0 dropped \(publishing errors 0; Zenoh session",
                     run.stdout), run.stdout
    assert [m["seq"] for m in got] == list(range(1, len(rows) + 1))
    pressed = 0
    for row, m in zip(rows, got):
        msg = m["message"]
        assert len(msg["contacts"]) == (int(row["n_contacts"]) if row["contact"] == "1" else 0)
        if msg["contacts"]:
            pressed += 1
            c = msg["contacts"][0]
            for key, digits in (("x_mm", 4), ("y_mm", 4), ("major_mm", 4), ("minor_mm", 4), ("angle_deg", 3),
                                ("strength", 3), ("depth_mm", 4), ("force_n", 4)):
                shown = "" if c[key] is None else f"{c[key]:.{digits}f}"
                assert shown == row[key], (row["frame"], key)
            assert c["id"] == int(row["contact_id"]) and c["shape"] == row["shape"]
    assert pressed > 100
    status = [m for m in _received(out) if m["topic"] == "/optitac/thumb/status"]
    assert status and status[-1]["message"]["frames"] == 300


def test_two_boards_are_two_peers_and_a_subscriber_sees_both_robots(tmp_path):
    port = free_port()
    out = tmp_path / "received.jsonl"
    sub = _subscriber(port, out)
    runs = [subprocess.Popen([sys.executable, "-m", "optitac_edge.cli", "run", "--board",
                              str(_board(tmp_path, robot, '[sensor]\nname = "hand"', port, f'namespace = "/{robot}"\n')),
                              "--frames", "60"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            for robot in ("robot1", "robot2")]
    for r in runs:
        _, err = r.communicate(timeout=120)
        assert r.returncode == 0, err[-2000:]
    sub.wait(60)
    topics = {m["topic"] for m in _received(out)}
    assert {"/robot1/optitac/hand/contacts", "/robot2/optitac/hand/contacts",
            "/robot1/optitac/hand/status", "/robot2/optitac/hand/status"} <= topics


def test_pictures_are_the_sensors_region_its_surface_and_the_overlay(store):
    for name in (msgs.IMAGE, msgs.ANNOTATIONS):
        store.register(get_types_from_msg(msgs.ros2msg_schema(name), name))
    s = sensor(5, "index")
    region = (10, 20, 30, 40)
    px = np.column_stack([5 + 2 * s.x_mm, 7 - 2 * s.y_mm]).astype(np.float64)
    placed = NetworkSensor(5, "index", s.x_mm, s.y_mm, s.dead, fiber_px=px, region=region, image_rows=100)
    frame = (np.arange(150 * 80) % 251).astype(np.uint8).reshape(150, 80)  # a YUV420 frame: 100 luma rows
    pub = VirtualPublisher()
    with NetworkOutput(pub, [placed], picture_hz=5) as net:
        for k in range(3):  # at 5 per second, frames 100 ms apart: pictures of frames 0 and 2
            net.offer_frame(5, frame_(k, contact(1, k, 0), t_ns=k * 100_000_000), False,
                            frame=frame, surface=np.full((4, 4), k, np.float32))
    images = [store.deserialize_cdr(m.payload, msgs.IMAGE) for m in pub.taken("/optitac/index/image")]
    assert len(images) == 2 and (images[0].width, images[0].height) == (30, 40)
    np.testing.assert_array_equal(np.frombuffer(bytes(images[0].data), np.uint8).reshape(40, 30),
                                  frame[20:60, 10:40])
    surfaces = [store.deserialize_cdr(m.payload, msgs.IMAGE) for m in pub.taken("/optitac/index/surface")]
    assert [np.frombuffer(bytes(x.data), "<f4")[0] for x in surfaces] == [0.0, 2.0]
    (overlay, _) = [store.deserialize_cdr(m.payload, msgs.ANNOTATIONS) for m in pub.taken("/optitac/index/annotations")]
    assert len(overlay.points[0].points) == 7 and overlay.texts[0].text == "1"
    cx, cy = overlay.texts[0].position.x, overlay.texts[0].position.y
    assert (cx, cy) == pytest.approx((5 + 2 * 1.0, 7 - 2 * -1.0))  # the contact at (1, -1) mm
    assert net.counters(5) == (3 + 2 * 3, 0)  # 3 Contacts, 2 pictures of 3 messages


def _router(endpoint: str):
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"router"')
    cfg.insert_json5("listen/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


def test_a_router_that_is_not_up_yet_is_joined_when_it_comes_and_nothing_waits_for_it():
    """The edge board boots before the robot's main computer: a Zenoh client cannot open its session yet.
    That must not stop the service (it used to exit 2, so systemd restarted it in a loop and the MCU
    heard nothing): the session is tried again from the publishing thread, 1 s, then 2 s, ... later."""
    import time

    from optitac_edge.io.clock import VirtualClock
    from optitac_edge.io.publishers.zenoh import ZenohPublisher

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    clock = VirtualClock()
    pub = ZenohPublisher(mode="client", connect=(endpoint,), clock=clock)
    router = None
    try:
        assert not pub.connected and pub.attempts == 1 and "Unable to connect" in pub.failure
        handle = pub.advertise("/optitac/thumb/contacts", msgs.CONTACTS)
        with pytest.raises(PublishError, match="no Zenoh session yet"):
            pub.publish(handle, b"\x00\x01\x00\x00", 0)
        assert pub.attempts == 1  # not again before its time
        clock.advance(1.0)
        with pytest.raises(PublishError):
            pub.publish(handle, b"\x00\x01\x00\x00", 0)
        assert pub.attempts == 2  # tried at 1 s; the next wait is 2 s
        clock.advance(1.5)
        with pytest.raises(PublishError):
            pub.publish(handle, b"\x00\x01\x00\x00", 0)
        assert pub.attempts == 2
        router = _router(endpoint)
        got: list[str] = []
        router.declare_subscriber("**", lambda sample: got.append(str(sample.key_expr)))
        clock.advance(0.5)
        deadline = time.monotonic() + 10
        while not got and time.monotonic() < deadline:  # the subscription reaches the client asynchronously
            pub.publish(handle, b"\x00\x01\x00\x00", 0)
            time.sleep(0.05)
        assert pub.connected and pub.attempts == 3 and pub.zid in pub.where
        assert got and got[0] == pub.keyexprs[handle]  # the topic declared when the session opened
    finally:
        pub.close()
        if router is not None:
            router.close()


@pytest.mark.parametrize("endpoint, words", [
    ("tcp/127.0.0.1:70000", "port 70000 is outside 1..65535"), ("foo/bar", "unknown protocol 'foo'"),
    ("tcp/127.0.0.1", "HOST:PORT"), ("tcp/:7447", "HOST:PORT"), ("tcp/::1:7447", "in brackets"),
])
def test_an_endpoint_that_can_never_work_is_refused_at_start(endpoint, words, tmp_path, capsys):
    """tcp/127.0.0.1:70000 and foo/bar were tried again for ever (every 30 s) instead of refused."""
    from optitac_edge.cli import main
    from optitac_edge.io.publishers.zenoh import ZenohPublisher, endpoint_problem

    with pytest.raises(PublishError, match=words):
        ZenohPublisher(mode="client", connect=(endpoint,))
    board = tmp_path / "b.toml"
    board.write_text(f'[publish.zenoh]\nmode = "client"\nconnect = ["{endpoint}"]\n')
    assert main(["run", "--board", str(board), "--duration", "5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0]
    assert endpoint_problem("tcp/[::1]:7447") == "" and endpoint_problem("tcp/0.0.0.0:0", listen=True) == ""
    assert endpoint_problem("udp/robot.local:7447") == "" and endpoint_problem("serial//dev/ttyUSB0") == ""


def test_run_streams_to_the_mcu_while_the_router_is_not_up(tmp_path):
    from fakes.mcu import FakeMcu

    board = tmp_path / "client.toml"
    board.write_text(f'[link]\ntransport = "serial"\n[publish.zenoh]\nmode = "client"\n'
                     f'connect = ["tcp/127.0.0.1:{free_port()}"]\n')
    mcu = FakeMcu()
    try:
        proc = subprocess.Popen([sys.executable, "-m", "optitac_edge.cli", "run", "--board", str(board), "--serial",
                                 mcu.path, "--frames", "120"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                text=True)
        frames = mcu.read_until(lambda fr: sum(f.type == MsgType.CONTACT for f in fr) >= 120, timeout=90)
        out, err = proc.communicate(timeout=60)
    finally:
        mcu.close()
    assert proc.returncode == 0, err[-2000:]
    assert sum(f.type == MsgType.CONTACT for f in frames) == 120  # every frame reached the MCU
    assert "cannot open a session yet" in err and "0 messages published" in out
