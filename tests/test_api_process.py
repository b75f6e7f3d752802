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
        with pytest.raises(ot.OptiTacError, match="timeout_s must be a finite number"):
            sensor.read(-1)
        with pytest.raises(ot.OptiTacError, match="wait_s must be a finite number"):
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
