"""The bring-up on the ``real`` physics (issue 37): snapshot sessions of a 61-fiber sensor whose fibers wander,
calibrated on one day and scored on another. ``tools/real_table.py`` runs it at full length for
docs/accuracy.md; this is a shorter one."""

from __future__ import annotations

import math
import shutil

import pytest

from optitac_edge.calibration.evaluation import centroid_accuracy, detection
from optitac_edge.calibration.measure import measure_sessions
from optitac_edge.cli import main
from optitac_edge.io.bundle_file import load_bundle
from optitac_edge.io.recording import Recording
from optitac_edge.sim.scenarios import write_scenario

FRAMES = 110  # about half an hour of snapshots each


@pytest.fixture(scope="module")
def days(tmp_path_factory):
    root = tmp_path_factory.mktemp("realbringup")
    rec = {day: [write_scenario(root / f"d{day}-{k}", "snapshots", seed=10 * day + k, day=day, physics="real",
                                frames=FRAMES) for k in range(2 if day == 1 else 1)] for day in (1, 2)}
    assert main(["layout", "--rings", "4", "--pitch-mm", "4", "-o", str(root / "hex61.csv")]) == 0
    return root, rec


def test_levels_from_the_presses_hold_on_another_day_where_the_rest_noise_fails(days, capsys) -> None:
    """Calibrated from day 1 (fibers, levels, orientation, centroid) and scored on day 2: presses found, rest
    frames minutes from their baseline quiet, location within a quarter pitch; the levels of the rest frames'
    noise alone made most of those rest frames contacts."""
    root, rec = days
    cal, noise_only = root / "cal.npz", root / "noise.npz"
    day1 = [str(p) for p in rec[1]]
    assert main(["calibrate", "fibers", day1[0], "-o", str(cal), "--layout", str(root / "hex61.csv")]) == 0
    shutil.copy(cal, noise_only)
    for step in ("levels", "orientation", "centroid"):
        assert main(["calibrate", step, *day1, "--cal", str(cal)]) == 0, capsys.readouterr()
    bundle = load_bundle(cal)
    assert bundle.options.on_level > 0 and bundle.extra_meta["levels"]["heldout_detection"] > 0.9
    day2 = [Recording(p) for p in rec[2]]
    m, truth = measure_sessions(day2, bundle)
    d, c = detection(m, truth), centroid_accuracy(m, truth)
    assert d.rest_frames > 15 and d.contact_frames > 50
    assert d.detected / d.contact_frames >= 0.9 and d.false_contacts / d.rest_frames <= 0.05, d
    assert math.hypot(c.rmse_x, c.rmse_y) <= 0.25 * bundle.layout.pitch_mm
    before = detection(*measure_sessions(day2, load_bundle(noise_only)))
    assert before.false_contacts / before.rest_frames > 0.5
