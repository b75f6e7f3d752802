"""The API for a control loop (issue 40): a sensor read in the background, the newest reading taken without
waiting and the others counted, a tare that waits for the baseline, unknown values that read as such, and the
simulated board's live sliding scenario."""

from __future__ import annotations

import itertools
import math
import queue
import re
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import optitac_edge as ot
from optitac_edge.api.background import BackgroundReader


def _reading(frame: int, ready: bool = True) -> ot.Reading:
    return ot.Reading(0, frame, frame * 1000, (), (), math.nan, False, ready, False)


class _Script:
    """A step the test feeds: each reading put is made once; ``None`` put: the step waits until released."""

    def __init__(self) -> None:
        self.items: queue.Queue[object] = queue.Queue()
        self.release = threading.Event()
        self.tares = 0

    def step(self, timeout_s: float) -> tuple[ot.Reading | None, bool]:
        try:
            item = self.items.get(timeout=timeout_s)
        except queue.Empty:
            return None, False
        if item == "end":
            return None, True
        if isinstance(item, Exception):
            raise item
        assert isinstance(item, ot.Reading)
        return item, False

    def tare(self) -> None:
        self.tares += 1


def _until(condition, what: str) -> None:
    """Wait until ``condition()`` (the reader's thread gets there; no figure depends on how fast)."""
    deadline = time.monotonic() + 30.0
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.001)


def test_latest_is_the_newest_reading_once_and_the_replaced_ones_are_counted():
    script = _Script()
    reader = BackgroundReader(script.step, script.tare, 0.05, "test-reader")
    try:
        assert reader.take(0.0) is None  # nothing read yet: at once, not waiting
        for k in range(3):
            script.items.put(_reading(k))
        _until(lambda: reader.made == 3, "three readings made")
        assert reader.take(0.0).frame == 2  # the newest
        assert (reader.returned, reader.unread) == (1, 2)
        assert reader.take(0.0) is None  # returned once only
        script.items.put(_reading(3))
        assert reader.take(5.0).frame == 3  # waits for the next one
        script.items.put(_reading(4))
        _until(lambda: reader.made == 5, "a fifth reading")
    finally:
        reader.stop()
    # the newest, never returned, is counted when the reader stops: every reading returned or counted
    assert (reader.made, reader.returned, reader.unread) == (5, 2, 3)
    assert not reader.running


def test_a_camera_failure_in_the_background_is_raised_once_by_the_next_take():
    script = _Script()
    reader = BackgroundReader(script.step, script.tare, 0.05, "test-reader")
    script.items.put(_reading(0))
    script.items.put(ot.OptiTacError("camera 'sim': no frame within 1.000 s"))
    _until(lambda: not reader.running, "the thread ended")
    assert reader.take(0.0).frame == 0  # the reading made before the failure first
    with pytest.raises(ot.OptiTacError, match="no frame within"):
        reader.take(0.0)
    assert reader.take(0.0) is None
    reader.stop()
    reader.stop()  # idempotent


def test_a_tare_in_the_background_is_made_by_the_reader_and_waits_for_a_ready_baseline():
    script = _Script()
    reader = BackgroundReader(script.step, script.tare, 0.05, "test-reader")
    try:
        assert reader.tare(None) is False  # asked, not waited for
        _until(lambda: script.tares == 1, "the reader's thread tared")
        script.items.put(_reading(0, ready=False))
        assert reader.tare(0.0) is False  # no ready reading since
        _until(lambda: script.tares == 2, "the second tare")
        done: list[bool] = []
        waiter = threading.Thread(target=lambda: done.append(reader.tare(30.0)))
        waiter.start()
        _until(lambda: script.tares == 3, "the third tare")
        script.items.put(_reading(1, ready=False))
        script.items.put(_reading(2, ready=True))
        waiter.join(30.0)
        assert done == [True]
    finally:
        reader.stop()


def test_a_recording_read_in_the_background_loses_nothing_silently(slide_rec: Path, bundle_path: Path):
    before = set(threading.enumerate())
    with ot.open_sensor(recording=slide_rec, cal=bundle_path) as sensor:
        with pytest.raises(ot.OptiTacError, match="call start"):
            sensor.latest()
        sensor.start()
        sensor.start()  # idempotent
        with pytest.raises(ot.OptiTacError, match=r"read in the background \(start\(\)\): read\(\)"):
            sensor.read()
        taken = []
        while (reading := sensor.latest(timeout_s=5.0)) is not None:
            taken.append(reading.frame)
            time.sleep(0.002)  # a loop slower than the replay: most readings are replaced before taken
        sensor.stop()
        status = sensor.status()
        assert sensor.read() is None  # read() again after stop(): the recording has ended
    assert status.frames == 1200 and status.skipped == 0
    assert status.unread == status.frames - len(taken) and status.unread > 0
    assert taken == sorted(set(taken)) and taken[-1] <= 1199
    assert {t for t in set(threading.enumerate()) - before if t.is_alive()} == set()  # no thread left behind
    with pytest.raises(ot.OptiTacError, match="closed"):
        sensor.start()


@pytest.fixture(scope="module")
def slide_rec(tmp_path_factory) -> Path:
    from optitac_edge.cli import main

    out = tmp_path_factory.mktemp("api-bg") / "slide"
    assert main(["sim", str(out), "--scenario", "slide", "--frames", "1200", "--storage", "fibers"]) == 0
    return out


def _fast_sim(**options: object) -> ot.Sensor:
    """The simulated board, its frames as fast as rendered (not at 240 fps in real time)."""
    return ot.open_sensor("sim", settings={"camera.fps": 240, "camera.options.realtime": False,
                                           **{f"camera.options.{k}": v for k, v in options.items()}})


def test_a_tare_waits_until_the_baseline_is_ready_in_either_mode():
    with _fast_sim() as sensor:
        assert sensor.tare(wait_s=60.0) is True
        waited = sensor.status()
        assert waited.baseline_ready and waited.unread == waited.frames  # read while waiting, counted
        assert sensor.tare() is False and not sensor.status().baseline_ready
        sensor.start()
        assert sensor.tare(wait_s=60.0) is True
        after = sensor.latest(timeout_s=10.0)
        assert after is not None and after.baseline_ready


def test_the_simulated_board_slides_live_and_refuses_an_unknown_scenario():
    """At the camera's pace (the slides' speeds are in mm/s of frame time): the slides at 2, 5 and 10 mm/s.

    The window is the camera's own time, not the reading loop's: frame k is stamped ``t0 + k / fps`` with the
    stream's ``t0`` after ``before`` (and moved later, never earlier, when the camera resynchronises), so a frame
    stamped less than 7.0 s after ``before`` shows the scenario before 7.0 s, ahead of its 20 mm/s slide (7.01 s)
    however long the sensor took to open on a busy machine (it was 5 s of readings after the open: flaky)."""
    before = time.monotonic_ns()
    with ot.open_sensor("sim", settings={"camera.fps": 240, "camera.options.scenario": "slide"}) as sensor:
        readings = list(itertools.takewhile(lambda r: r.t_ns - before < 7_000_000_000,
                                            sensor.readings(duration_s=10.0)))
    sliding = [c for r in readings for c in r.contacts if c.sliding]
    assert len(sliding) > 100 and all(c.has_velocity for c in sliding)
    speeds = np.array([math.hypot(c.vx_mm_s, c.vy_mm_s) for c in sliding])
    # the slides' own speeds; a lift's few frames may read faster (its centroid moves as the contact shrinks)
    assert 1.0 < float(np.median(speeds)) < 10.0 and np.mean(speeds < 15.0) > 0.9
    with pytest.raises(ot.OptiTacError, match=r"^simulated camera: unknown scenario 'spin' \(presses, slide, "):
        _fast_sim(scenario="spin")


def test_unknown_values_read_as_unknown():
    nan = math.nan
    blind = ot.Contact(1, 0, 0.5, 0.5, 3.0, 2.0, 0.0, 10.0, nan, nan, "", nan, nan, nan, False, -1)
    assert not (blind.has_depth or blind.has_force or blind.has_shape or blind.has_velocity)
    known = ot.Contact(1, 0, 0.5, 0.5, 3.0, 2.0, 0.0, 10.0, 1.2, 0.8, "circle", 0.9, 0.0, nan, False, -1)
    assert known.has_depth and known.has_force and known.has_shape and not known.has_velocity
    reading = ot.Reading(0, 5, 0, (known,), (), nan, False, True, False)
    assert reading.touching and not reading.has_vibration
    assert not ot.Reading(0, 6, 0, (), (), 1.0, False, True, False).touching


def test_a_sensor_opened_with_arrays_gives_each_readings_fibers_and_surface(slide_rec: Path, bundle_path: Path):
    from optitac_edge.calibration.measure import replay_recording
    from optitac_edge.core.pipeline import Pipeline
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.recording import Recording

    bundle = load_bundle(bundle_path)
    rec = Recording(slide_rec)
    pipe = Pipeline(bundle, fps=rec.meta.fps)
    want = [(pipe.signal.copy(), pipe.surface / pipe.levels.trunc) for _ in replay_recording(rec, pipe)]
    with ot.open_sensor(recording=slide_rec, cal=bundle_path, arrays=True) as sensor:
        got = list(sensor.readings())
    assert len(got) == len(want) == 1200
    for reading, (fibers, surface) in zip(got, want):
        np.testing.assert_array_equal(reading.fibers, fibers)
        np.testing.assert_array_equal(reading.surface, surface)
    assert max(float(r.surface.max()) for r in got) > 1.0  # presses above the contact threshold
    assert got[0].fibers is not got[1].fibers and got[0] == got[0]  # arrays of their own; readings still compare
    with ot.open_sensor(recording=slide_rec, cal=bundle_path) as sensor:
        plain = sensor.read()
    assert plain.fibers is None and plain.surface is None


def test_the_control_loop_example_takes_the_newest_reading_every_tick_and_leaves_no_thread():
    """examples/control_loop.py, briefly: exit 0 means every tick's reading was the newest, the counts add up and
    no thread was left; the drops it prints while the loop ran and before it are the sensor's own counter."""
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[1] / "examples" / "control_loop.py"
    done = subprocess.run([sys.executable, str(script), "--seconds", "2", "--hz", "20", "--fps", "60"],
                          check=False, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    lines = done.stdout.splitlines()
    assert lines[0] == "loop: 40 ticks at 20 Hz over 2 s, camera at 60 fps"  # however late the ticks come
    assert re.fullmatch(r"frames processed (\d+) = taken (\d+) \+ unread (\d+): yes; camera dropped \d+ while the "
                        r"loop ran \(\d+ while the sensor opened\), skipped 0", lines[2])
    assert lines[3] == "threads left after close(): 0"
