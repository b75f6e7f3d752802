"""Recordings as a LeRobot dataset (issue 40): the features of a frame, the export's one-line refusals, and (where
LeRobot's writer is installed: CI's LeRobot environment, ``.ci/run``) a dataset written by LeRobot's writer and
read back by LeRobot's loader equal, value for value, to the contacts CSV of the same recordings."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from optitac_edge.cli import main
from optitac_edge.core.options import MAX_CONTACTS
from optitac_edge.devtools import lerobot_features as lf

HAS_LEROBOT = importlib.util.find_spec("ledataset") is not None
needs_lerobot = pytest.mark.skipif(not HAS_LEROBOT, reason="LeRobot's writer (pip install 'optitac-edge[lerobot]'): "
                                   "runs in CI's LeRobot environment, the lerobot step of .ci/run")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, Path, Path]:
    """A 240-fps slide recording (with truth), its bundle and its contacts CSV (``replay``)."""
    d = tmp_path_factory.mktemp("lerobot")
    assert main(["sim", str(d / "slide"), "--scenario", "slide", "--frames", "720"]) == 0
    assert main(["calibrate", "fibers", str(d / "slide"), "-o", str(d / "cal.npz")]) == 0
    assert main(["replay", str(d / "slide"), "--cal", str(d / "cal.npz"), "-o", str(d / "slide.csv")]) == 0
    return d / "slide", d / "cal.npz", d / "slide.csv"


def test_the_features_are_named_and_a_frame_fills_every_slot_strongest_first(recorded):
    from optitac_edge.calibration.measure import replay_recording
    from optitac_edge.core.pipeline import Pipeline
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.recording import Recording

    rec_path, cal, _ = recorded
    bundle = load_bundle(cal)
    features = lf.tactile_features(bundle.layout.ids, video=True, truth_shapes=["circle", ""])
    assert features[lf.CONTACTS]["names"][:2] == ["contact0.present", "contact0.x_mm"]
    assert features[lf.CONTACTS]["shape"] == (MAX_CONTACTS * len(lf.CONTACT_FIELDS),)
    assert features[lf.FIBERS]["names"][0] == f"fiber{bundle.layout.ids[0]}" and features[lf.FIBERS]["shape"] == (217,)
    assert features[lf.TRUTH_SHAPE]["names"] == ["none", "circle"]
    rec = Recording(rec_path)
    pipeline = Pipeline(bundle, fps=rec.meta.fps)
    seen_contact = False
    for i, result in replay_recording(rec, pipeline):
        values = lf.frame_values(result, pipeline.signal)
        slots = values[lf.CONTACTS].reshape(MAX_CONTACTS, len(lf.CONTACT_FIELDS))
        n = result.n_contacts
        assert list(slots[:, 0]) == [1.0] * n + [0.0] * (MAX_CONTACTS - n)
        assert not slots[n:].any()  # an empty slot is all zeros
        for slot, c in zip(slots, result.touching()):
            assert slot[1] == c.x_mm and slot[11] == c.contact_id and slot[10] == float(c.sliding)
        assert values[lf.T_NS][0] == result.t_ns == rec.t_ns[i]
        assert np.array_equal(values[lf.FIBERS], pipeline.signal) and values[lf.FIBERS] is not pipeline.signal
        seen_contact |= n >= 1
        truth = lf.truth_values(rec.truth, lf.truth_rows(rec.truth)[i], ["none", "circle"])
        assert truth[lf.TRUTH][0] == float(rec.truth.contact[i])
        assert truth[lf.TRUTH_SHAPE][0] == (1 if rec.truth.contact[i] else 0)
    assert seen_contact
    image = lf.surface_image(pipeline.surface + 100.0, 50.0)
    assert image.shape == (224, 224, 3) and image.dtype == np.uint8 and (image == 255).all()


def test_a_rigs_truth_fills_the_frames_it_has_rows_for_and_leaves_the_moves_unknown(tmp_path):
    """A rig's recording has truth rows for its holds only (the export once indexed the rows by frame number and
    ended in an IndexError on a full collect seen)."""
    from optitac_edge.io.recording import Recording

    assert main(["collect", "seen", "--rig", "sim://", "-o", str(tmp_path / "seen"), "--limit", "2"]) == 0
    rec = Recording(tmp_path / "seen")
    assert len(rec.truth) < len(rec)  # rows for some frames only
    rows = lf.truth_rows(rec.truth)
    names = lf.shape_names([str(s) for s in rec.truth.shape])
    held = [i for i in range(len(rec)) if i in rows and rec.truth.contact[rows[i]]]
    assert held
    for i in range(len(rec)):
        got = lf.truth_values(rec.truth, rows.get(i), names)
        if i not in rows:
            assert np.isnan(got[lf.TRUTH]).all() and got[lf.TRUTH_SHAPE][0] == 0
        else:
            k = rows[i]
            assert got[lf.TRUTH][0] == float(rec.truth.contact[k])
            assert got[lf.TRUTH][1] == rec.truth.x_mm[k] or not rec.truth.contact[k]
            assert names[got[lf.TRUTH_SHAPE][0]] == (str(rec.truth.shape[k]) or "none")


def test_the_export_refuses_in_one_line(recorded, tmp_path, capsys):
    rec, cal, _ = recorded
    existing = tmp_path / "ds"
    existing.mkdir()
    assert main(["export-lerobot", str(rec), "--cal", str(cal), "-o", str(existing)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists; a dataset is written to a new directory" in err[0]
    assert main(["export-lerobot", str(rec), "--cal", str(cal), "-o", str(tmp_path / "x"), "--repo-id", "a/b/c"]) != 0
    assert "--repo-id must be OWNER/NAME" in capsys.readouterr().err
    if not HAS_LEROBOT:  # the extra missing: one line naming it, nothing written
        assert main(["export-lerobot", str(rec), "--cal", str(cal), "-o", str(tmp_path / "new")]) != 0
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "pip install 'optitac-edge[lerobot]'" in err[0] and "Traceback" not in err[0]
        assert not (tmp_path / "new").exists()


def test_recordings_of_several_rates_are_one_line():
    from types import SimpleNamespace

    from optitac_edge.devtools.lerobot_export import whole_fps
    from optitac_edge.errors import OptiTacError

    def rec(fps):
        return SimpleNamespace(meta=SimpleNamespace(fps=fps))

    assert whole_fps([rec(240.0), rec(240.0)]) == 240
    with pytest.raises(OptiTacError, match=r"one frame rate; these recordings have \[60.0, 240.0\]"):
        whole_fps([rec(240.0), rec(60.0)])
    with pytest.raises(OptiTacError, match="whole number; the recordings' is 59.94 fps"):
        whole_fps([rec(59.94)])


@needs_lerobot
@pytest.mark.lerobot
# LeRobot stores a (1,) feature as a scalar through datasets, which converts each array with int(): numpy's warning
@pytest.mark.filterwarnings("ignore:Conversion of an array with ndim > 0 to a scalar:DeprecationWarning")
def test_an_export_read_back_by_lerobots_loader_equals_the_contacts_csv(recorded, roundtrip_tool, tmp_path,
                                                                         capsys):
    from ledataset.datasets.lerobot_dataset import LeRobotDataset

    rec, cal, contacts_csv = recorded
    out = tmp_path / "ds"
    assert main(["export-lerobot", str(rec), str(rec), "--cal", str(cal), "-o", str(out), "--video"]) == 0
    said = capsys.readouterr().out
    assert said.startswith(f"wrote {out}: 2 episodes, 1440 frames, ") and "per 1 000 frames" in said
    frames, compared, differ = roundtrip_tool.compare(out, [contacts_csv, contacts_csv])
    assert (frames, differ) == (1440, 0) and compared > 1440 * 6
    ds = LeRobotDataset("optitac/tactile", root=out)
    assert ds.meta.total_episodes == 2 and len(ds) == 1440 and ds.fps == 240
    assert ds.meta.features[lf.STATE]["names"] == list(lf.STATE_FIELDS)
    assert ds.meta.features[lf.IMAGE]["dtype"] == "video"
    # LeRobot's own item access (torch tensors, the video decoded): the same frame
    item = ds[720 + 300]
    table = ds.hf_dataset.with_format(None)
    assert int(item[lf.T_NS]) == int(table[300][lf.T_NS]) and tuple(item[lf.IMAGE].shape) == (3, 224, 224)
    assert not list(tmp_path.glob(".ds.*partial")) and not list(tmp_path.glob(".ds.partial"))


@needs_lerobot
@pytest.mark.lerobot
@pytest.mark.filterwarnings("ignore:Conversion of an array with ndim > 0 to a scalar:DeprecationWarning")
def test_the_roundtrip_check_finds_a_changed_value(recorded, roundtrip_tool, tmp_path):
    """The comparison is not vacuous: one value changed in the CSV is one difference."""
    rec, cal, contacts_csv = recorded
    out = tmp_path / "ds"
    assert main(["export-lerobot", str(rec), "--cal", str(cal), "-o", str(out)]) == 0
    lines = contacts_csv.read_text().splitlines()
    row = next(k for k, line in enumerate(lines) if line.split(",")[1] == "1")
    cells = lines[row].split(",")
    cells[2] = f"{float(cells[2]) + 0.0001:.4f}"  # x_mm, one unit of its last digit
    changed = tmp_path / "changed.csv"
    changed.write_text("\n".join([*lines[:row], ",".join(cells), *lines[row + 1:]]) + "\n")
    assert roundtrip_tool.compare(out, [changed])[2] == 1


def test_the_checking_tools_refuse_a_workdir_that_exists_in_one_line(roundtrip_tool, tmp_path, capsys):
    """The checks write a new dataset: an existing directory (perhaps the last run's) is one line, not a
    traceback, and is left as it was."""
    from conftest import load_tool

    kept = tmp_path / "kept.txt"
    kept.write_text("the last run")
    for argv in ([str(tmp_path), "--cal", "cal.npz", "--workdir", str(tmp_path)], ["--workdir", str(tmp_path)]):
        tool = roundtrip_tool if "--cal" in argv else load_tool("lerobot_record_check")
        with pytest.raises(SystemExit) as exited:
            tool.main(argv)
        assert exited.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert err.endswith(f"error: --workdir {tmp_path}: exists (give a new directory)")
    assert kept.read_text() == "the last run"
