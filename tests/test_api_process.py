"""A sensor in a process of its own (``open_sensor_process``, issue 40): the same readings as ``open_sensor``, the
same errors as one line, nothing left behind (no thread here, no child) however it ends."""

from __future__ import annotations

import os
import signal
import threading
import time
from dataclasses import astuple
from pathlib import Path

import pytest
from test_api import BAD_INPUT

import optitac_edge as ot
from optitac_edge.api import sensor_process
from optitac_edge.errors import CameraError


@pytest.fixture(scope="module")
def slide_rec(tmp_path_factory) -> Path:
    from optitac_edge.cli import main

    out = tmp_path_factory.mktemp("api-process") / "slide"
    assert main(["sim", str(out), "--scenario", "slide", "--frames", "300", "--storage", "fibers"]) == 0
    return out


def _gone(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    return False


def test_a_recording_reads_the_same_in_a_process_as_here_and_nothing_is_left(slide_rec: Path, bundle_path: Path):
    with ot.open_sensor(recording=slide_rec, cal=bundle_path, arrays=True) as here:
        want = list(here)
        want_status = here.status()
    before = set(threading.enumerate())
    with ot.open_sensor_process(recording=slide_rec, cal=bundle_path, arrays=True) as there:
        assert there.pid != os.getpid() and (there.sensor_id, there.name) == (here.sensor_id, here.name)
        got = list(there)
        status = there.status()
        assert set(threading.enumerate()) == before  # the parent keeps no thread
        pid = there.pid
    assert len(got) == len(want) == 300 and any(r.contacts for r in got)
    # each reading's values, its contacts and arrays included, as here (velocities to their last bits: they are
    # fitted on the frames' absolute times, which a replay moves to the moment it is opened)
    assert [(r.frame, r.released, r.baseline_ready, [c.id for c in r.contacts]) for r in got] == \
        [(r.frame, r.released, r.baseline_ready, [c.id for c in r.contacts]) for r in want]
    numbers = [v for r in got for c in r.contacts for v in astuple(c) if not isinstance(v, str)]
    assert numbers == pytest.approx([v for r in want for c in r.contacts for v in astuple(c) if not isinstance(v, str)],
                                    rel=1e-9, abs=1e-8, nan_ok=True)
    assert all((a.fibers == b.fibers).all() and (a.surface == b.surface).all() for a, b in zip(got, want))
    assert [r.t_ns - got[0].t_ns for r in got] == [r.t_ns - want[0].t_ns for r in want]
    assert (status.frames, status.contact_frames, status.skipped) == \
        (want_status.frames, want_status.contact_frames, want_status.skipped)
    assert _gone(pid)
    there.close()  # idempotent
    with pytest.raises(ot.OptiTacError, match="closed"):
        there.status()


def test_the_background_reader_runs_in_the_child_and_counts_what_it_replaced(slide_rec: Path, bundle_path: Path):
    with ot.open_sensor_process(recording=slide_rec, cal=bundle_path) as sensor:
        with pytest.raises(ot.OptiTacError, match="call start"):  # the child's error, raised here as it is
            sensor.latest()
        sensor.start()
        taken = []
        while (reading := sensor.latest(timeout_s=5.0)) is not None:
            taken.append(reading.frame)
            time.sleep(0.005)
        status = sensor.status()
        assert sensor.tare() is False
    assert status.frames == 300 and status.unread == status.frames - len(taken) and status.unread > 0
    assert taken == sorted(set(taken))


@pytest.mark.parametrize(("kwargs", "message"), [*BAD_INPUT, ({"settings": {"camera.fps": lambda: 1}},
                                                                 "cannot be sent to the sensor's process")])
def test_what_open_sensor_refuses_is_refused_in_one_line_and_the_child_ends(kwargs, message):
    with pytest.raises(ot.OptiTacError, match=message) as caught:
        ot.open_sensor_process(**kwargs)
    assert "\n" not in str(caught.value)


def test_a_child_that_dies_is_one_line_and_the_next_call_says_closed(slide_rec: Path, bundle_path: Path):
    sensor = ot.open_sensor_process(recording=slide_rec, cal=bundle_path)
    os.kill(sensor.pid, signal.SIGKILL)
    with pytest.raises(ot.OptiTacError, match=r"its process ended \(exit status -9\)"):
        sensor.read()
    with pytest.raises(ot.OptiTacError, match="closed"):
        sensor.read()
    sensor.close()
    assert _gone(sensor.pid)


def test_the_child_ends_by_itself_when_its_parent_lets_go(slide_rec: Path, bundle_path: Path):
    """The parent's end of the socket closed without a word (as when the parent dies): the child closes its
    sensor and ends."""
    sensor = ot.open_sensor_process(recording=slide_rec, cal=bundle_path)
    sensor._conn.close()
    assert sensor._process.wait(timeout=30) == 0


def test_bad_arguments_to_a_call_are_the_sensors_own_one_line_errors(slide_rec: Path, bundle_path: Path):
    with ot.open_sensor_process(recording=slide_rec, cal=bundle_path) as sensor:
        with pytest.raises(ot.OptiTacError, match="timeout_s must be a number of seconds in 0..1e\\+09"):
            sensor.read(-1)
        with pytest.raises(ot.OptiTacError, match="wait_s must be a number of seconds in 0..1e\\+09"):
            sensor.tare(float("nan"))
        with pytest.raises(ot.OptiTacError, match="has no call 'close_camera'"):
            sensor._call("close_camera")
        with pytest.raises(ot.OptiTacError, match=r"read\(\): its arguments cannot be sent"):
            sensor.read(lambda: 1.0)  # type: ignore[arg-type]
        assert sensor.read() is not None  # still answering


def test_the_childs_program_refuses_a_missing_descriptor():
    assert sensor_process.main([]) == 2
    assert sensor_process.main(["x"]) == 2


def test_a_ctrl_c_to_the_process_group_leaves_the_child_to_its_parent(slide_rec: Path, bundle_path: Path, capfd):
    """Ctrl-C at a terminal signals every process of the group: the child printed a KeyboardInterrupt traceback
    and died; now the parent decides (its own KeyboardInterrupt closes the sensor, or its exit ends the child)."""
    with ot.open_sensor_process(recording=slide_rec, cal=bundle_path) as sensor:
        assert sensor.read() is not None
        os.kill(sensor.pid, signal.SIGINT)
        assert sensor.read() is not None  # still answering
        pid = sensor.pid
    assert _gone(pid)
    assert "Traceback" not in capfd.readouterr().err


def test_a_reading_crosses_as_data_exactly_and_nothing_is_pickled():
    """The messages are JSON and raw array bytes (tests/test_reliability_files.py: the package never unpickles);
    every float crosses to the bit, NaN included."""
    import math
    from multiprocessing import Pipe
    from pathlib import Path as P

    import numpy as np

    from optitac_edge.api import sensor_messages as messages

    contact = ot.Contact(3, 7, 0.1 + 0.2, -1e-300, 2.5, 1.25, 89.99999999999999, 1 / 3, math.nan, math.nan, "sphere",
                         math.nan, -4.828011272464382, 5e-324, True, 9)
    reading = ot.Reading(2, 12, 2**62, (contact,), (4, 5), math.nan, True, True, False,
                         fibers=np.linspace(0, 1, 217, dtype=np.float32),
                         surface=np.arange(100 * 100, dtype=np.float32).reshape(100, 100) / 7)
    status = ot.Status(2, "thumb", 10, 4, 1, True, "abc", True, 240.0, 3, 7)
    a, b = Pipe()
    for value in (reading, status, None, True, (2, "thumb", 1.5)):
        messages.send_answer(a, value)
        got = messages.recv_answer(b)
        assert repr(got) == repr(value)
    messages.send_answer(a, reading)
    back = messages.recv_answer(b)
    assert isinstance(back, ot.Reading) and back.fibers.dtype == np.float32 and back.surface.shape == (100, 100)
    assert (back.fibers == reading.fibers).all() and (back.surface == reading.surface).all()
    assert back.surface.flags.writeable  # a copy, as the sensor's own readings
    messages.send_answer(a, CameraError("camera main: no frame within 1 s"))
    with pytest.raises(CameraError, match="no frame within 1 s"):
        messages.recv_answer(b)
    messages.send_answer(a, ValueError("boom"))
    with pytest.raises(ot.OptiTacError, match="the sensor process failed: ValueError: boom"):
        messages.recv_answer(b)
    for path in ("sensor_process.py", "sensor_messages.py"):
        text = (P(sensor_process.__file__).parent / path).read_text()
        assert ".recv()" not in text and ".send(" not in text  # multiprocessing's pickling pair


@pytest.mark.parametrize(("header", "blobs", "message"), [
    (b"\xff", [], "not JSON"),
    (b"[1, 2]", [], "not a JSON object"),
    (b'{"kind": "telnet", "id": 0}', [], "no known kind"),
    (b'{"kind": "none"}', [], "an answer numbered None"),
    (b'{"kind": "none", "id": -1}', [], "an answer numbered -1"),
    (b'[' * 100000 + b']' * 100000, [], "nested too deeply"),
    (b'{"kind": "status", "id": 0, "fields": {"frames": 1}}', [], "malformed status"),
    (b'{"kind": "reading", "id": 0, "fields": {}, "contacts": [], "released": [], "arrays": {"fibers": ["|O", [2]]}}', [b"xx"],
     "malformed reading"),
    (b'{"kind": "reading", "id": 0, "fields": {}, "contacts": [], "released": [], "arrays": {"fibers": ["<f4", [3]]}}',
     [b"12345678"], "8 bytes for an array"),
])
def test_a_malformed_answer_is_one_line(header, blobs, message):
    from multiprocessing import Pipe

    from optitac_edge.api import sensor_messages as messages

    a, b = Pipe()
    a.send_bytes(header)
    for blob in blobs:
        a.send_bytes(blob)
    with pytest.raises(messages.MalformedMessage, match=message):
        messages.recv_answer(b)
