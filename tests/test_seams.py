"""Issue 52 §5: the rest of the sweep, each with a test that failed before it."""

from __future__ import annotations

import json
import shutil
import threading
import tracemalloc
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_fingerprint import _one_line

import optitac_edge as ot
from optitac_edge.cli import main
from optitac_edge.core.layout import FiberLayout, hex_layout
from optitac_edge.errors import OptiTacError, OutputError, RecordingError
from optitac_edge.io.recording import Recording


@pytest.mark.parametrize("frames", [10**18, 2**64, 10**6])
def test_a_tare_past_the_recordings_end_is_refused(unseen_rec, tmp_path, frames):
    """Before: accepted, and it silenced every later contact (127 -> 60 contact frames)."""
    rec = tmp_path / "rec"
    shutil.copytree(unseen_rec, rec)
    meta = json.loads((rec / "meta.json").read_text())
    meta["tares"] = [{"frame": 20, "frames": frames}]
    (rec / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(RecordingError, match=r"tares\[0\].*K >= 1 frames the recording has from F on"):
        Recording(rec)
    meta["tares"] = [{"frame": 20, "frames": len(Recording(unseen_rec)) - 20}]  # to the very end: fine
    (rec / "meta.json").write_text(json.dumps(meta))
    assert Recording(rec).tares[0].frames == len(Recording(unseen_rec)) - 20


def test_a_collinear_layout_is_refused_by_the_parser(tmp_path, capsys):
    """Before: it passed the parser, then ``sim --layout`` died with QhullError."""
    csv = tmp_path / "line.csv"
    csv.write_text("fiber,x_mm,y_mm\n" + "".join(f"{i},{1.5 * i},0\n" for i in range(10)))
    _one_line(capsys, ["sim", str(tmp_path / "out"), "--layout", str(csv), "--scenario", "rest"],
              "the fibers lie on one line")
    with pytest.raises(ValueError, match="one line"):  # a tilted line too
        FiberLayout(ids=np.arange(9), xy_mm=np.c_[np.arange(9) * 1.0, np.arange(9) * 2.0])


def test_a_20000_fiber_layout_takes_memory_in_proportion_to_its_fibers():
    """Before: N x N distance matrices (6 GB for 20 000 fibers), then an allocation error."""
    tracemalloc.start()
    try:
        layout = hex_layout(rings=81, pitch_mm=0.5)
        pitch, pairs = layout.pitch_mm, layout.neighbour_pairs()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert layout.n_fibers == 19927 and pitch == pytest.approx(0.5) and len(pairs) == 59292
    assert peak < 200 * layout.n_fibers * 8  # ~32 MB; N x N float64 would be 3.2 GB


@settings(max_examples=60, deadline=None)
@given(n=st.integers(7, 400), seed=st.integers(0, 2**32 - 1))
def test_neighbours_are_the_brute_force_ones(n, seed):
    rng = np.random.default_rng(seed)
    xy = np.unique(np.round(rng.uniform(-30, 30, (n, 2)), 3), axis=0)
    if len(xy) < 7:
        return
    try:
        layout = FiberLayout(ids=np.arange(len(xy)), xy_mm=xy)
    except ValueError:
        return  # too close or on a line: refused as the parser would
    d = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1))
    np.fill_diagonal(d, np.inf)
    assert layout.pitch_mm == pytest.approx(float(np.median(d.min(axis=1))))
    limit = 1.2 * layout.pitch_mm
    for i, got in enumerate(layout.neighbours()):
        np.testing.assert_array_equal(got, np.flatnonzero(d[i] <= limit))


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"cal": 3}, "cal must be a path (str or os.PathLike), got int 3"),
    ({"recording": 7}, "recording must be a path (str or os.PathLike), got int 7"),
    ({"settings": {1: 2}}, "settings: a key must be 'section.key' (a str), got int 1"),
])
def test_open_sensor_arguments_of_the_wrong_type_are_one_line(kwargs, message):
    """Before: TypeError and AttributeError tracebacks."""
    for opener in (ot.open_sensor, ot.open_sensor_process):
        with pytest.raises(OptiTacError) as info:
            opener("sim", **kwargs)
        assert str(info.value) == message


def test_readings_for_1e308_seconds_is_one_line():
    """Before: OverflowError."""
    with ot.open_sensor("sim") as sensor, pytest.raises(OptiTacError, match=r"duration_s must be a number of "
                                                                          r"seconds in 0\.\.1e\+09, got 1e\+308"):
        next(sensor.readings(duration_s=1e308))


def test_a_journal_time_near_2_63_is_refused():
    from optitac_edge.bringup.journal import MAX_T_NS, _check_entry

    rows = [{"frame": k, "phase": "rest", "rig": [0.0, 0.0, 5.0]} for k in range(2)]
    entry = {"kind": "press", "index": 0, "end_frame": 2, "rows": rows, "t_ns": [0, 2**63 - 1]}
    assert "frame times" in _check_entry(entry, False, 0, 0)
    entry["t_ns"] = [0, MAX_T_NS - 1]
    assert "frame times" not in _check_entry(entry, False, 0, 0)


def test_a_recording_writer_refuses_a_time_it_cannot_hold(tmp_path):
    from optitac_edge.io.recording import RecordingMeta
    from optitac_edge.io.recording_writer import RecordingWriter

    writer = RecordingWriter(tmp_path / "rec", None, (4, 4), RecordingMeta(rest_frames=1, fps=10.0))
    with pytest.raises(OutputError, match="not a time this recording can hold"):
        writer.write(0, np.zeros((4, 4), np.uint8), 2**63 + 5)
    writer.abort("test")


class _FakeDataset:
    """LeRobot's writer as export-lerobot uses it (create, add_frame, save_episode, finalize), writing files."""

    started = threading.Event()
    release = threading.Event()

    @classmethod
    def create(cls, repo_id, fps, features, root, robot_type, use_videos):
        root = Path(root)
        root.mkdir(parents=True, exist_ok=False)  # as LeRobot's: the root must not exist
        return cls(root)

    def __init__(self, root):
        self.root, self.rows = root, 0

    def add_frame(self, row):
        self.rows += 1
        if self.rows == 5:
            type(self).started.set()
            type(self).release.wait(10)

    def save_episode(self):
        (self.root / "episode.txt").write_text(str(self.rows))

    def finalize(self):
        pass


def test_export_lerobot_keeps_a_users_partial_folder_and_takes_one_writer(unseen_rec, bundle_path, tmp_path,
                                                                         monkeypatch):
    """Before: it deleted a user's own ``.NAME.partial`` folder, and two exports to one destination ran into each
    other."""
    from optitac_edge.devtools import lerobot_export as ex

    monkeypatch.setattr(ex, "_load_writer", lambda: _FakeDataset)
    mine = tmp_path / ".ds.partial"
    mine.mkdir()
    (mine / "notes.txt").write_text("the user's")
    job = ex.ExportJob(recordings=(unseen_rec,), bundle=bundle_path, output=tmp_path / "ds")
    _FakeDataset.started.clear()
    _FakeDataset.release.clear()
    errors: list[BaseException] = []

    def first():
        try:
            ex.export_lerobot(job, progress=False)
        except BaseException as exc:  # noqa: BLE001
            errors.append(exc)

    t = threading.Thread(target=first)
    t.start()
    assert _FakeDataset.started.wait(30)
    with pytest.raises(OutputError, match="another optitac-edge is writing it now"):
        ex.export_lerobot(job, progress=False)  # the second writer, while the first writes
    _FakeDataset.release.set()
    t.join(60)
    assert not errors and (tmp_path / "ds" / "episode.txt").exists()
    assert (mine / "notes.txt").read_text() == "the user's"  # not ours: kept
    assert [p for p in tmp_path.glob(".ds.*partial")] == [mine]  # ours: gone


def test_no_array_the_kernel_points_into_can_be_resized_under_it(bundle_path, rest_rec):
    """Before: a plan's ``means`` resized (``refcheck=False``) after the kernel took it gave heap-use-after-free
    in gray_means (kernel/frame_kernel.c, under AddressSanitizer). Now every such array has a weak reference,
    and numpy refuses to resize it."""
    from optitac_edge.core.compiled import CompiledEngine, _arrays_of
    from optitac_edge.core.pipeline import Pipeline
    from optitac_edge.io.bundle_file import load_bundle

    pipe = Pipeline(load_bundle(bundle_path), compiled=True)
    assert isinstance(pipe.engine, CompiledEngine)
    held = _arrays_of(pipe.engine.plan.as_dict())
    assert any(a is pipe.engine.plan.means for a in held) and len(held) > 10
    for a in held:
        with pytest.raises(ValueError, match="cannot resize"):
            a.resize(a.size * 1000 + 1000, refcheck=False)
    rec = Recording(rest_rec)
    for i in range(8):
        pipe.process_recorded(rec.frame(i), i * 10**7)  # the kernel's buffers are still where it points


def test_a_recording_keeps_its_layout_and_calibrate_fibers_uses_it(tmp_path, capsys):
    """Issue 52 §6: ``calibrate fibers`` on a 61-fiber recording said ``found 61 of 217 fibers in the rest frames
    (is the LED on?)``. Now the recording keeps the layout it was made with, and a map that finds another count
    says what it found and what to try."""
    from optitac_edge.io.layout_csv import save_layout_csv

    layout = hex_layout(rings=4, pitch_mm=4.0)
    csv = tmp_path / "hex61.csv"
    save_layout_csv(layout, csv)
    assert main(["sim", str(tmp_path / "r61"), "--scenario", "rest", "--layout", str(csv)]) == 0
    rec = Recording(tmp_path / "r61")
    assert rec.layout is not None and np.array_equal(rec.layout.ids, layout.ids)
    from optitac_edge.io.layout_csv import load_layout_csv

    assert np.array_equal(rec.layout.xy_mm, load_layout_csv(csv).xy_mm)  # exactly the CSV's
    assert main(["calibrate", "fibers", str(tmp_path / "r61"), "-o", str(tmp_path / "cal.npz")]) == 0
    assert "61/61 fibers found" in capsys.readouterr().out
    meta = json.loads((tmp_path / "r61" / "meta.json").read_text())
    del meta["layout"]  # a recording made before layouts were kept
    (tmp_path / "r61" / "meta.json").write_text(json.dumps(meta))
    _one_line(capsys, ["calibrate", "fibers", str(tmp_path / "r61"), "-o", str(tmp_path / "cal2.npz")],
              "found 61 of the layout's 217 fibers", "61 bright spots centred at", "px apart",
              "needs its own layout (--layout CSV")
    meta["layout"] = {"fiber": [1, 2], "x_mm": [0.0], "y_mm": [0.0, 1.0]}
    (tmp_path / "r61" / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(RecordingError, match="'layout' must be"):
        Recording(tmp_path / "r61")


def test_messages_name_what_the_user_gave(capsys):
    """Issue 52 §5: a bad settings= key said 'command line: camera.fsp'; camera.timeout_s = 5e-324 was accepted,
    then 'no frame within 0.000 s'."""
    with pytest.raises(OptiTacError, match=r"^settings: camera\.fsp: unknown key"):
        ot.open_sensor("sim", settings={"camera.fsp": 3})
    from optitac_edge.config import load_board_config
    from optitac_edge.errors import ConfigError

    with pytest.raises(ConfigError, match=r"camera\.timeout_s: must be a number in 0\.001\.\.60, got 5e-324"):
        load_board_config("sim", env={"OPTITAC_CAMERA_TIMEOUT_S": "5e-324"})
    with pytest.raises(SystemExit):
        main(["monitor", "--help"])
    assert "protocol 1|2|3" in " ".join(capsys.readouterr().out.split())  # argparse wraps the help


def test_a_relative_camera_option_path_is_the_board_files(tmp_path, monkeypatch):
    """Issue 52 §6: a relative ``[camera.options] layout`` resolved against the working directory (the systemd
    unit runs in /), while [calibration] paths resolved against the file."""
    from optitac_edge.config import load_board_config
    from optitac_edge.io.layout_csv import save_layout_csv

    board_dir = tmp_path / "etc"
    board_dir.mkdir()
    save_layout_csv(hex_layout(rings=4, pitch_mm=4.0), board_dir / "hex61.csv")
    (board_dir / "board.toml").write_text('[camera]\nbackend = "sim"\n[camera.options]\nlayout = "hex61.csv"\n'
                                          '[calibration]\nbundle = "cal.npz"\nlayout = "hex61.csv"\n')
    elsewhere = tmp_path / "run"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    config = load_board_config(board_dir / "board.toml", env={})
    assert config.camera.options["layout"] == str(board_dir / "hex61.csv")
    with ot.open_sensor(str(board_dir / "board.toml")) as sensor:
        assert sensor._pipeline.bundle.layout.n_fibers == 61  # calibrated at open from the 61-fiber camera
        assert sensor.read(2.0) is not None  # its frames fit: the camera simulated the 61-fiber array


def test_record_keeps_the_boards_layout(tmp_path, capsys):
    from optitac_edge.io.layout_csv import save_layout_csv

    save_layout_csv(hex_layout(rings=4, pitch_mm=4.0), tmp_path / "hex61.csv")
    board = tmp_path / "board.toml"
    board.write_text('[camera]\nbackend = "sim"\n[camera.options]\nlayout = "hex61.csv"\n'
                     '[calibration]\nlayout = "hex61.csv"\nbundle = "cal.npz"\n')
    assert main(["record", "--board", str(board), "-o", str(tmp_path / "rec"), "--frames", "20"]) == 0
    rec = Recording(tmp_path / "rec")
    assert rec.layout is not None and rec.layout.n_fibers == 61
    assert main(["calibrate", "fibers", str(tmp_path / "rec"), "-o", str(tmp_path / "c.npz")]) == 0
    assert "61/61 fibers found" in capsys.readouterr().out


def test_long_steps_say_their_progress_where_no_bar_is_shown(unseen_rec, bundle_path, tmp_path, caplog,
                                                             monkeypatch):
    """Issue 52 §6: long steps printed nothing when the output was not a terminal (calibrate levels 10 min)."""
    import logging

    from optitac_edge.calibration import measure

    monkeypatch.setattr(measure, "PROGRESS_S", 0.0)
    caplog.set_level(logging.DEBUG)
    assert main(["replay", str(unseen_rec), "--cal", str(bundle_path), "-o", str(tmp_path / "c.csv")]) == 0
    said = [r.getMessage() for r in caplog.records if r.name == "optitac_edge.progress" and r.levelno >= logging.INFO
            and logging.getLogger(r.name).isEnabledFor(r.levelno)]
    assert "replay: frame 64 of 448 (14 %)" in said, said
    caplog.clear()
    assert main(["-q", "replay", str(unseen_rec), "--cal", str(bundle_path), "-o", str(tmp_path / "d.csv")]) == 0
    assert not logging.getLogger("optitac_edge.progress").isEnabledFor(logging.INFO)
    logging.getLogger("optitac_edge.progress").setLevel(logging.NOTSET)


def _with_meta(src: Path, dst: Path, **edits: object) -> Path:
    shutil.copytree(src, dst)
    meta = json.loads((dst / "meta.json").read_text())
    (dst / "meta.json").write_text(json.dumps({**meta, **edits}))
    return dst


def test_a_stated_rate_the_frame_times_deny_is_refused(unseen_rec, tmp_path, monkeypatch):
    """Before: an fps edited 60 -> 90 (in meta.json or an MCAP's metadata) was taken, and frames all 1 ns apart
    set ``vibrating`` on most frames; now both are one line naming the file and the rate."""
    from optitac_edge.io.recording_mcap import recording_to_mcap

    fps = Recording(unseen_rec).meta.fps
    stamped = _with_meta(unseen_rec, tmp_path / "stamped")
    n = len(Recording(stamped))
    np.save(stamped / "timestamps.npy", np.round(np.arange(n) * 1e9 / fps).astype(np.int64))
    assert Recording(stamped).timestamped  # its own times: accepted
    edited = _with_meta(stamped, tmp_path / "edited", fps=fps * 1.5)
    with pytest.raises(RecordingError, match=rf"edited/meta.json: 'fps' is {fps * 1.5:g} but its frames are "
                                             rf"16.67 ms apart \(60 fps, lower quartile of {n - 1} intervals\)"):
        Recording(edited)
    one_ns = _with_meta(stamped, tmp_path / "one_ns")
    np.save(one_ns / "timestamps.npy", np.arange(n, dtype=np.int64))
    with pytest.raises(RecordingError, match=r"frames are 1e-06 ms apart \(1e\+09 fps"):
        Recording(one_ns)
    # a camera that lost two frames after every one it kept: half its intervals are three periods
    lossy = _with_meta(stamped, tmp_path / "lossy")
    periods = np.concatenate([[0], np.cumsum(np.where(np.arange(n - 1) % 2 == 0, 1, 3))])
    np.save(lossy / "timestamps.npy", np.round(periods * 1e9 / fps).astype(np.int64))
    assert Recording(lossy).meta.fps == fps
    mcap = recording_to_mcap(Recording(stamped), tmp_path / "s.mcap")
    assert Recording(mcap).meta.fps == fps
    rec = Recording(stamped)
    rec.meta = replace(rec.meta, fps=90.0)
    # the metadata as an editor leaves it (this program's writer states the rate the times show)
    monkeypatch.setattr("optitac_edge.io.recording_mcap.state_rate_shown", lambda meta, t_ns, where: None)
    with pytest.raises(RecordingError, match=r"e.mcap: 'fps' is 90 but its frames are 16.67 ms apart"):
        Recording(recording_to_mcap(rec, tmp_path / "e.mcap"))


def test_rest_frames_over_a_press_are_refused(unseen_rec, tmp_path):
    """Before: rest_frames edited 10 -> 39 took the baseline from a press; now refused by the truth."""
    from optitac_edge.io.recording_mcap import recording_to_mcap

    rec = Recording(unseen_rec)
    assert rec.truth is not None
    first = int(np.flatnonzero(rec.truth.contact)[0])
    over = _with_meta(unseen_rec, tmp_path / "over", rest_frames=first + 3)
    with pytest.raises(RecordingError, match=rf"over/meta.json: 'rest_frames' is {first + 3} but its truth has a "
                                             rf"contact at frame {first}: the rest frames must be contact-free"):
        Recording(over)
    rec.meta = replace(rec.meta, rest_frames=first + 3)
    with pytest.raises(RecordingError, match=rf"o.mcap: 'rest_frames' is {first + 3} but its truth has a contact"):
        Recording(recording_to_mcap(rec, tmp_path / "o.mcap"))


def test_the_snapshot_gap_is_the_contact_options_default():
    from optitac_edge.core.options import ContactOptions
    from optitac_edge.io.recording_rate import SNAPSHOT_GAP_NS

    assert SNAPSHOT_GAP_NS == round(ContactOptions().gap_s * 1e9)


def test_a_recording_whose_writer_was_killed_claims_no_frame_count(tmp_path):
    """Before: a fibers recording killed after 33 s said '0 of 400 frames written' (the count its marker had
    at the start); a writer that never finished cannot say how far it got, and the line says why."""
    from optitac_edge.io.recording import RecordingMeta
    from optitac_edge.io.recording_writer import RecordingWriter

    w = RecordingWriter(tmp_path / "r", 400, (6, 8), RecordingMeta(rest_frames=5, fps=50.0))
    for i in range(30):
        w.write(i, np.zeros((6, 8), np.uint8), 20_000_000 * i)
    with pytest.raises(RecordingError) as refused:  # as after SIGKILL: the writer never closes
        Recording(tmp_path / "r")
    assert str(refused.value) == (f"{tmp_path / 'r'}: incomplete recording (its writer stopped without finishing: "
                                  "killed, crashed or the power lost while it wrote); record it again")
    w.abort("interrupted")
    with pytest.raises(RecordingError, match=r"\(interrupted: 30 of 400 frames written\)"):
        Recording(tmp_path / "r")


def test_a_writer_states_the_rate_its_camera_delivered(tmp_path, caplog):
    """A camera asked for 60 fps that delivers 30 (auto exposure in dim light) made a recording its reader
    refuses ('fps' is 60 but its frames are 33.33 ms apart); every writer states the rate the times show and
    keeps the asked one."""
    from optitac_edge.io.recording import RecordingMeta
    from optitac_edge.io.recording_mcap import McapRecordingWriter
    from optitac_edge.io.recording_rate import FPS_ASKED_KEY
    from optitac_edge.io.recording_writer import RecordingWriter

    meta = RecordingMeta(rest_frames=5, fps=60.0)
    times = [round(i * 1e9 / 30) for i in range(40)]
    with caplog.at_level("WARNING", logger="optitac_edge.io.recording_rate"):
        with RecordingWriter(tmp_path / "d", 40, (6, 8), meta) as w:
            for i, t in enumerate(times):
                w.write(i, np.zeros((6, 8), np.uint8), t)
        with McapRecordingWriter(tmp_path / "m.mcap", meta.to_json()) as m:
            for i, t in enumerate(times):
                m.write(i, np.zeros((6, 8), np.uint8), t)
    for path in (tmp_path / "d", tmp_path / "m.mcap"):
        rec = Recording(path)
        assert rec.meta.fps == 30.0 and rec.meta.extra[FPS_ASKED_KEY] == 60.0
    warned = [r.getMessage() for r in caplog.records]
    assert len(warned) == 2 and all("the camera delivered 30 frames/s, not the 60 asked for" in w for w in warned)
    with RecordingWriter(tmp_path / "ok", 40, (6, 8), meta) as w:  # a camera at its rate: nothing added
        for i in range(40):
            w.write(i, np.zeros((6, 8), np.uint8), round(i * 1e9 / 60))
    assert FPS_ASKED_KEY not in Recording(tmp_path / "ok").meta.extra
