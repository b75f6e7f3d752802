"""A calibration job reads, calibrates and saves in one call (what ``optitac-edge calibrate`` runs)."""

from __future__ import annotations

import pytest

from optitac_edge.calibration.jobs import FiberMapJob, StepJob, map_fibers
from optitac_edge.core.region import Region
from optitac_edge.errors import OptiTacError
from optitac_edge.io.bundle_file import load_bundle, readable_bundle
from optitac_edge.io.recording import Recording


def test_frames_of_another_size_than_the_boards_camera_are_refused_before_anything_is_written(rest_rec, tmp_path):
    rec = Recording(rest_rec)
    out = tmp_path / "cal.npz"
    job = FiberMapJob(rest_rec, out, Region(0, 0, 200, 200), ("sensor left's camera 'main'", 1280, 720))
    with pytest.raises(OptiTacError, match=rf"frames are {rec.width}x{rec.height}, sensor left's camera 'main' "
                                           r"delivers 1280x720"):
        map_fibers(job)
    assert not out.exists()


def test_a_file_that_is_no_bundle_is_replaced_without_its_orientation(rest_rec, tmp_path):
    out = tmp_path / "cal.npz"
    out.write_bytes(b"not a bundle")
    assert readable_bundle(out) is None and readable_bundle(tmp_path / "absent.npz") is None
    done = map_fibers(FiberMapJob(rest_rec, out))
    assert not done.kept and not done.lost
    assert load_bundle(out).calibration_id == done.bundle.calibration_id
    assert done.bundle.fibers.dead.sum() == 0


def test_an_unknown_step_is_refused_naming_the_steps(tmp_path):
    with pytest.raises(ValueError, match="unknown calibration step 'colour' .one of orientation, levels"):
        StepJob("colour", (tmp_path,), tmp_path / "cal.npz")
