"""The pieces of the paced harness (tools/pace_run.py): a recording played as a DMA camera, the loop's stage
times, threads named where the operating system shows them."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest

from optitac_edge.cli import main
from optitac_edge.errors import CameraError
from optitac_edge.io.cameras.recording import RecordingCamera
from optitac_edge.io.recording import RecordingMeta
from optitac_edge.io.recording_writer import RecordingWriter
from optitac_edge.io.threads import NamedThread, name_this_thread
from optitac_edge.service.stage_times import StageTimes


def _rec(path: Path, n: int, fps: float = 1000.0) -> Path:
    with RecordingWriter(path, n, (6, 8), RecordingMeta(rest_frames=5, fps=fps)) as w:
        for i in range(n):
            w.write(i, np.full((6, 8), i, np.uint8), i * 1_000_000)
    return path


def test_a_live_recording_delivers_every_frame_in_order_then_ends(tmp_path):
    with RecordingCamera(_rec(tmp_path / "r", 10), realtime=True, live=True, queue_frames=16) as cam:
        got = [cam.read() for _ in range(11)]
    frames = got[:10]
    assert got[10] is None
    assert [int(c.frame[0, 0]) for c in frames if c is not None] == list(range(10))
    assert all(c is not None and not c.frame.flags.writeable for c in frames)  # the memory map's bytes
    assert cam.frames_dropped == 0


def test_a_live_recording_drops_and_counts_the_frames_the_loop_did_not_take(tmp_path):
    """As a camera's queue: the oldest waiting frame goes when queue_frames newer ones wait; the gap in seq
    is the camera's drop count."""
    cam = RecordingCamera(_rec(tmp_path / "r", 10), realtime=True, live=True, queue_frames=2)
    try:
        cam._thread.join(timeout=10)  # the whole recording played before the loop read anything
        first, second, end = cam.read(), cam.read(), cam.read()
    finally:
        cam.close()
    assert first is not None and second is not None and end is None
    assert (int(first.frame[0, 0]), int(second.frame[0, 0])) == (8, 9)
    assert cam.overwritten == 8 and cam.frames_dropped == 0  # the first frame read sets the sequence
    assert (first.seq, second.seq) == (9, 10)


def test_live_needs_realtime_and_a_valid_queue(tmp_path):
    rec = _rec(tmp_path / "r", 6)
    with pytest.raises(CameraError, match="live needs realtime"):
        RecordingCamera(rec, live=True)
    with pytest.raises(CameraError, match="queue_frames"):
        RecordingCamera(rec, realtime=True, live=True, queue_frames=0)


def test_stage_times_keep_each_frame_and_summarise_them():
    ticks = iter(range(0, 10_000_000, 1000))
    times = StageTimes(clock=lambda: next(ticks), capacity=4)
    for k in range(6):  # the last 4 kept: 2..5
        times.add(1000 * (k + 1), 500)
    s = times.summary()
    assert s["frames"] == 4
    assert s["pipeline"] == {"median_us": 4.5, "mean_us": 4.5, "p99_us": pytest.approx(5.97)}
    assert s["send"]["median_us"] == 0.5
    assert times.clock() == 0  # the injected clock


def test_run_writes_the_loops_stage_times(tmp_path, capsys):
    out = tmp_path / "stages.json"
    assert main(["run", "--fps", "1000", "--frames", "60", "--stage-times", str(out)]) == 0
    (lead,) = json.loads(out.read_text())
    assert lead["frames_processed"] == 60 and lead["sensors"] == 1
    assert lead["pipeline"]["median_us"] > 0 and lead["send"]["median_us"] > 0
    assert lead["kernel"] in ("compiled", "numpy")


def test_a_thread_names_itself_for_the_operating_system():
    seen: list[str] = []

    def work() -> None:
        assert name_this_thread("optitac-a-long-thread-name")
        seen.append(Path(f"/proc/self/task/{threading.get_native_id()}/comm").read_text().strip())

    t = threading.Thread(target=work)
    t.start()
    t.join()
    assert seen == ["optitac-a-long-"]  # the kernel keeps 15 bytes


def test_run_times_its_start_up_at_debug_level(tmp_path, caplog) -> None:
    """``run -v``: each phase of the start-up in the log, in order, each at or after the one before."""
    import logging

    from optitac_edge.io.startup import STARTUP

    STARTUP.marks.clear()
    with caplog.at_level(logging.DEBUG, logger="optitac_edge.startup"):
        assert main(["run", "--fps", "1000", "--frames", "5"]) == 0
    phases = [m[0] for m in STARTUP.marks]
    assert phases == ["imports", "board config", "cameras opened", "link opened", "bundles",
                      "pipelines and kernel plans", "first frame of camera main"]
    ages = [m[1] for m in STARTUP.marks]
    assert ages == sorted(ages) and ages[0] > 0
    assert sum("start-up: bundles done" in r.getMessage() for r in caplog.records) == 1


def test_the_services_threads_carry_their_names_to_the_operating_system():
    """A NamedThread (every thread the service starts) shows its Python name in /proc, as ``top -H`` does."""
    seen: list[str] = []

    def work() -> None:
        seen.append(Path(f"/proc/self/task/{threading.get_native_id()}/comm").read_text().strip())

    t = NamedThread(target=work, name="optitac-serial-tx", daemon=True)
    t.start()
    t.join()
    assert seen == ["optitac-serial-"]
