"""Per-frame capture times, open-ended and continued recordings, rig columns in truth.csv."""

import csv
import subprocess
import sys

import numpy as np
import pytest

from optitac_edge.errors import RecordingError
from optitac_edge.io.recording import TIMESTAMPS, Recording, RecordingMeta
from optitac_edge.io.recording_writer import Press, RecordingWriter

META = RecordingMeta(rest_frames=5, fps=50.0)


def test_frame_times_are_saved_and_read_back(tmp_path):
    times = [1_000_000_000 + 19_000_000 * i + (i % 3) * 1000 for i in range(8)]
    with RecordingWriter(tmp_path / "r", 8, (6, 8), META) as w:
        for i, t in enumerate(times):
            w.write(i, np.full((6, 8), i, np.uint8), t)
    rec = Recording(tmp_path / "r")
    assert rec.timestamped and rec.t_ns.dtype == np.int64 and rec.t_ns.tolist() == times


def test_without_times_frames_are_at_their_nominal_times(tmp_path):
    with RecordingWriter(tmp_path / "r", 6, (6, 8), META) as w:
        for i in range(6):
            w.write(i, np.zeros((6, 8), np.uint8), None if i == 3 else i)
    rec = Recording(tmp_path / "r")
    assert not (tmp_path / "r" / TIMESTAMPS).exists() and not rec.timestamped
    assert rec.t_ns.tolist() == [0, 20_000_000, 40_000_000, 60_000_000, 80_000_000, 100_000_000]


@pytest.mark.parametrize("damage, message", [
    (lambda p: np.save(p / TIMESTAMPS, np.arange(3, dtype=np.int64)), r"shape \(6,\)"),
    (lambda p: np.save(p / TIMESTAMPS, np.arange(6, dtype=np.float64)), "int64"),
    (lambda p: np.save(p / TIMESTAMPS, np.array([0, 5, 4, 6, 7, 8], dtype=np.int64)), "backwards at frame 2"),
    (lambda p: (p / TIMESTAMPS).write_bytes(b"junk"), "garbled timestamps"),
])
def test_bad_timestamps_are_refused_in_one_line(tmp_path, damage, message):
    with RecordingWriter(tmp_path / "r", 6, (6, 8), META) as w:
        for i in range(6):
            w.write(i, np.zeros((6, 8), np.uint8), i)
    damage(tmp_path / "r")
    with pytest.raises(RecordingError, match=message):
        Recording(tmp_path / "r")


def test_an_open_ended_recording_holds_exactly_the_frames_written(tmp_path):
    with RecordingWriter(tmp_path / "r", None, (6, 8), META) as w:
        for i in range(600):  # grows past GROW_FRAMES twice
            w.write(i, np.full((6, 8), i % 251, np.uint8), 20_000_000 * i)
    rec = Recording(tmp_path / "r")
    assert len(rec) == 600 and [int(rec.frames[i][0, 0]) for i in (0, 300, 599)] == [0, 300 % 251, 599 % 251]
    assert (tmp_path / "r" / "frames.npy").stat().st_size == 128 + 600 * 48
    assert np.load(tmp_path / "r" / "frames.npy").shape == (600, 6, 8)


def test_an_interrupted_open_ended_recording_continues_after_its_kept_frames(tmp_path):
    path = tmp_path / "r"
    with pytest.raises(KeyboardInterrupt), RecordingWriter(path, None, (6, 8), META, with_truth=True) as w:
        for i in range(40):
            w.write(i, np.full((6, 8), i, np.uint8), 1000 + 20_000_000 * i)
        raise KeyboardInterrupt
    with pytest.raises(RecordingError, match="incomplete recording"):
        Recording(path)
    kept = 30  # e.g. the frames of the presses that were finished
    with RecordingWriter(path, None, (6, 8), META, with_truth=True, keep_frames=kept,
                         kept_t_ns=1000 + 20_000_000 * np.arange(kept)) as w:
        for i in range(kept):
            w.write_truth(i, None)
        for i in range(kept, 50):
            w.write(i, np.full((6, 8), 100 + i, np.uint8), 5000 + 20_000_000 * i)
            w.write_truth(i, None)
    rec = Recording(path)
    assert len(rec) == 50 and len(rec.truth) == 50
    assert [int(rec.frames[i][0, 0]) for i in (0, 29, 30, 49)] == [0, 29, 130, 149]
    assert rec.t_ns[29] == 1000 + 29 * 20_000_000 and rec.t_ns[30] == 5000 + 30 * 20_000_000


def test_continuing_needs_frames_of_the_same_shape(tmp_path):
    path = tmp_path / "r"
    with pytest.raises(KeyboardInterrupt), RecordingWriter(path, None, (6, 8), META) as w:
        w.write(0, np.zeros((6, 8), np.uint8), 0)
        raise KeyboardInterrupt
    with pytest.raises(RecordingError, match="cannot continue"):
        RecordingWriter(path, None, (6, 9), META, keep_frames=1, kept_t_ns=np.zeros(1, np.int64))


def test_rig_columns_keep_every_pose_and_score_only_rest_and_hold(tmp_path):
    phases = ["rest"] * 5 + ["approach", "hold", "hold", "release", "move"]
    with RecordingWriter(tmp_path / "r", None, (6, 8), RecordingMeta(rest_frames=5, fps=50.0),
                         rig_columns=True) as w:
        for i, phase in enumerate(phases):
            w.write(i, np.zeros((6, 8), np.uint8), 20_000_000 * i)
            pressed = phase in ("approach", "hold", "release")
            press = Press("circle", 1.0, 2.0, float("nan"), 5.0, 3.0 if phase == "hold" else 1.0) if pressed else None
            w.write_truth(i, press, phase=phase, rig_xyz_mm=(100.0, 50.0 + i, -3.0 if pressed else 2.0))
    rec = Recording(tmp_path / "r")
    assert rec.truth is not None and rec.rig_poses is not None
    assert rec.truth.frame.tolist() == [0, 1, 2, 3, 4, 6, 7] and rec.truth.depth_mm[5] == 3.0
    assert rec.rig_poses.phase.tolist() == phases and rec.rig_poses.xyz_mm[9].tolist() == [100.0, 59.0, 2.0]
    with (tmp_path / "r" / "truth.csv").open() as f:
        assert next(csv.reader(f))[-4:] == ["phase", "rig_x_mm", "rig_y_mm", "rig_z_mm"]


def test_an_unknown_phase_is_refused(tmp_path):
    with RecordingWriter(tmp_path / "r", 6, (6, 8), META, rig_columns=True) as w:
        for i in range(6):
            w.write(i, np.zeros((6, 8), np.uint8))
            w.write_truth(i, None, phase="rest", rig_xyz_mm=(0.0, 0.0, 5.0))
    text = (tmp_path / "r" / "truth.csv").read_text().replace("rest", "wobble", 1)
    (tmp_path / "r" / "truth.csv").write_text(text)
    with pytest.raises(RecordingError, match="line 2: unknown phase 'wobble'"):
        Recording(tmp_path / "r")


def test_replay_writes_each_frames_capture_time(tmp_path):
    from optitac_edge.cli import main

    rec = tmp_path / "rec"
    assert main(["sim", str(rec), "--scenario", "unseen", "--frames", "40"]) == 0
    assert main(["calibrate", "fibers", str(rec), "-o", str(tmp_path / "cal.npz")]) == 0
    assert main(["replay", str(rec), "--cal", str(tmp_path / "cal.npz"), "-o", str(tmp_path / "c.csv")]) == 0
    with (tmp_path / "c.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [int(r["t_ns"]) for r in rows] == Recording(rec).t_ns.tolist()
    assert int(rows[3]["t_ns"]) == round(3 * 1e9 / Recording(rec).meta.fps)


def test_record_saves_the_cameras_frame_times(tmp_path):
    out = tmp_path / "r"
    done = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "record", "-o", str(out), "--frames", "12"],
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    rec = Recording(out)
    assert rec.timestamped and np.all(np.diff(rec.t_ns) > 0)
    assert abs(np.median(np.diff(rec.t_ns)) - 1e9 / rec.meta.fps) < 0.2e9 / rec.meta.fps


def test_record_says_the_cameras_gaps_and_drops(tmp_path, capsys):
    """``record`` at 240 fps wrote 4 800 frames spanning 64 s with 229 gaps and said only 'wrote 4800 frames'
    (issue 38, item 24): it says the span, the gaps and the frames they would have held, as ``run`` does."""
    from optitac_edge.cli import main
    from optitac_edge.service.recorder import frame_gaps

    period = 1e9 / 240
    t = np.round(np.array([0, 1, 2, 5, 6, 7, 8, 20]) * period).astype(np.int64)  # 2 missing, then 11 missing
    assert frame_gaps(t, 240.0) == (2, 13)
    assert frame_gaps(np.arange(10) * round(period), 240.0) == (0, 0)
    assert main(["record", "-o", str(tmp_path / "r"), "--frames", "20"]) == 0
    out = capsys.readouterr().out
    assert "20 frames of 640x480 gray over" in out and "0 gaps (0 frames missing), 0 dropped by the camera" in out
