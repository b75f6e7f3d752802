"""Acceptance on the simulator's `unseen` scenario: detection, raw centroid accuracy, oracle agreement."""

from __future__ import annotations

import numpy as np
import pytest

from optitac_edge.calibration.evaluation import centroid_accuracy, detection, read_contacts_csv
from optitac_edge.cli import main
from optitac_edge.core.options import ContactOptions
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.devtools.reference import ReferencePipeline
from optitac_edge.io.bundle_file import load_bundle
from optitac_edge.io.recording import Recording


@pytest.fixture(scope="module")
def unseen_contacts(tmp_path_factory, unseen_rec, bundle_path):
    out = tmp_path_factory.mktemp("replay") / "contacts.csv"
    assert main(["replay", str(unseen_rec), "--cal", str(bundle_path), "-o", str(out)]) == 0
    return read_contacts_csv(out)


def test_contact_on_every_contact_frame_and_no_rest_frame(unseen_contacts, unseen_rec):
    truth = Recording(unseen_rec).truth
    report = detection(unseen_contacts, truth)
    print(report)
    assert report.contact_frames > 250
    assert report.detected == report.contact_frames
    assert report.false_contacts == 0


def test_raw_centroid_rmse_below_0_75_mm_per_axis(unseen_contacts, unseen_rec):
    report = centroid_accuracy(unseen_contacts, Recording(unseen_rec).truth)
    print(report)
    assert report.rmse_x < 0.75 and report.rmse_y < 0.75
    assert report.r2_x > 0.95 and report.r2_y > 0.95


def test_fast_pipeline_agrees_with_the_reference_on_every_frame(unseen_rec, bundle_path):
    rec = Recording(unseen_rec)
    bundle = load_bundle(bundle_path)
    fast, ref = Pipeline(bundle, ContactOptions.paper()), ReferencePipeline(bundle)  # the paper's method
    compared = 0
    worst_centroid = worst_width = 0.0
    for i in range(len(rec)):
        frame = rec.frame(i)
        a, b = fast.process_recorded(frame, i).primary, ref.process(frame, i).primary
        assert a.contact == b.contact, i
        if a.contact:
            compared += 1
            worst_centroid = max(worst_centroid, abs(a.x_mm - b.x_mm), abs(a.y_mm - b.y_mm))
            worst_width = max(worst_width, abs(a.major_mm / b.major_mm - 1), abs(a.minor_mm / b.minor_mm - 1))
    print(f"{compared} contact frames: max centroid diff {worst_centroid:.2e} mm, width {worst_width:.2e}")
    assert compared > 250
    assert worst_centroid < 0.02
    assert worst_width < 0.01


def test_five_dark_fibers_are_reported_dead_and_the_pipeline_still_runs(tmp_path, capsys):
    dark = "0,37,108,150,216"
    rest, unseen, cal, out = (tmp_path / n for n in ("rest", "unseen", "cal.npz", "c.csv"))
    assert main(["sim", str(rest), "--scenario", "rest", "--dark-fibers", dark, "--frames", "12"]) == 0
    assert main(["sim", str(unseen), "--scenario", "unseen", "--dark-fibers", dark, "--seed", "4",
                 "--frames", "120"]) == 0
    assert main(["calibrate", "fibers", str(rest), "-o", str(cal)]) == 0
    assert "212/217 fibers found; dead fibers 0, 37, 108, 150, 216;" in capsys.readouterr().out
    bundle = load_bundle(cal)
    assert sorted(np.flatnonzero(bundle.fibers.dead)) == [0, 37, 108, 150, 216]
    assert main(["replay", str(unseen), "--cal", str(cal), "-o", str(out)]) == 0
    truth = Recording(unseen).truth
    contacts = read_contacts_csv(out)
    report = detection(contacts, truth)
    assert report.detected == report.contact_frames and report.false_contacts == 0
    assert np.isfinite(contacts.x_mm[truth.frame[truth.contact]]).all()
