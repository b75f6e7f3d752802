"""A verdict on each calibration: the checks, their limits, and the report without raw dicts."""

from __future__ import annotations

import numpy as np
import pytest

from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.calibration.measure import measure_recording
from optitac_edge.calibration.steps import calibrate_centroid
from optitac_edge.calibration.verdict import bundle_checks, coverage, judge
from optitac_edge.cli import main
from optitac_edge.io.bundle_file import save_bundle
from optitac_edge.io.recording import Recording
from optitac_edge.sim.scenarios import write_scenario


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    wd = tmp_path_factory.mktemp("verdict")
    seen = Recording(write_scenario(wd / "seen", "seen", seed=3))
    fibers = calibrate_fibers(seen.rest_frames(), seen.pixel_format)
    bundle, _ = calibrate_centroid(seen, fibers)
    cal = wd / "cal.npz"
    save_bundle(bundle, cal)
    return wd, fibers, bundle, cal


def test_a_fiber_map_alone_is_not_good_enough_and_says_why(calibrated) -> None:
    _, fibers, _, _ = calibrated
    checks = {c.name: c for c in bundle_checks(fibers)}
    assert checks["fiber map"].ok and "0.0 % dead" in checks["fiber map"].seen
    assert not checks["orientation"].ok and "calibrate orientation" in checks["orientation"].fix
    assert not checks["coverage"].ok and checks["coverage"].seen == "no centroid calibration"


def test_a_seen_calibration_covers_the_array_and_checks_the_orientation(calibrated) -> None:
    _, _, bundle, _ = calibrated
    assert coverage(bundle) == 1.0
    checks = {c.name: c for c in bundle_checks(bundle)}
    assert checks["orientation"].ok and checks["coverage"].ok


def test_presses_near_the_centre_only_cover_too_little(calibrated, tmp_path) -> None:
    _, fibers, _, _ = calibrated
    repeat = Recording(write_scenario(tmp_path / "r", "unseen", seed=5))
    bundle, _ = calibrate_centroid(repeat, fibers)
    cov = coverage(bundle)
    assert cov is not None and cov < 0.5


def test_the_verdict_on_unseen_presses(calibrated, tmp_path, capsys) -> None:
    _, fibers, bundle, cal = calibrated
    unseen = Recording(write_scenario(tmp_path / "u", "unseen", seed=6))
    verdict = judge(bundle, measure_recording(unseen, bundle), unseen.truth)
    assert verdict.good, verdict.lines()
    assert main(["evaluate", str(unseen.path), "--cal", str(cal), "--strict"]) == 0
    assert "verdict: GOOD ENOUGH (every check passes)" in capsys.readouterr().out
    bare = tmp_path / "fibers.npz"
    save_bundle(fibers, bare)
    assert main(["evaluate", str(unseen.path), "--cal", str(bare), "--strict"]) == 1
    out = capsys.readouterr().out
    assert "verdict: NOT GOOD ENOUGH (orientation, coverage)" in out and "[FAIL] coverage" in out
    assert main(["evaluate", str(unseen.path), "--cal", str(bare)]) == 0  # without --strict: informative only


def test_the_report_has_a_verdict_and_no_raw_dicts(calibrated, tmp_path, capsys) -> None:
    _, _, _, cal = calibrated
    assert main(["report", str(cal), "-o", str(tmp_path / "rep")]) == 0
    # issue 38: the command ends with the verdict, as the bring-up guide says (and --strict as evaluate's)
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("wrote ") and out[1].startswith("verdict: ") and "[ok] coverage" in "\n".join(out)
    good = out[1] == "verdict: GOOD ENOUGH (every check passes)"
    assert main(["report", str(cal), "-o", str(tmp_path / "rep"), "--strict"]) == (0 if good else 1)
    text = (tmp_path / "rep" / "index.md").read_text()
    assert "## Verdict" in text and "[ok] coverage: 100 %" in text
    assert "{" not in text and "}" not in text and "[0." not in text
    # issue 26: the fills the map was chosen among, with their held-out figures, in a line of their own
    line = next(x for x in text.splitlines() if x.startswith("Centroid calibration, candidates"))
    assert "nearest " in line and "linear " in line and "'" not in line


def test_error_map_colours_are_on_the_scale_of_the_array() -> None:
    from types import SimpleNamespace

    from optitac_edge.calibration.report import array_colour_limit

    cm = SimpleNamespace(x0_mm=-20.0, y0_mm=-20.0, step_mm=1.0, n=41)
    data = np.zeros((41, 41), np.float32)
    data[20, 25] = 0.3  # inside the array (5 mm from the centre)
    data[0, 0] = 9.0  # the extrapolated corner
    assert array_colour_limit(data, cm, radius_mm=12.0) == pytest.approx(0.3)


def test_the_error_maps_grey_out_what_no_press_measured_and_mark_the_presses(calibrated, tmp_path) -> None:
    """The report's error maps painted corrections over areas never pressed, without marking the presses."""
    import cv2

    _, fibers, _, _ = calibrated
    lines = Recording(write_scenario(tmp_path / "u", "unseen", seed=5))  # presses along x and y only
    bundle, _ = calibrate_centroid(lines, fibers)
    cal = tmp_path / "lines.npz"
    save_bundle(bundle, cal)
    assert main(["report", str(cal), "-o", str(tmp_path / "report")]) == 0
    picture = cv2.imread(str(tmp_path / "report" / "error_maps.png"))
    grey = np.all(np.abs(picture.astype(int) - 0xD8) <= 2, axis=2)
    assert grey.mean() > 0.15  # most of the map: no press there
    from optitac_edge.calibration.report import _near_presses
    from optitac_edge.core.corrections import ContactCorrector

    cm = ContactCorrector(bundle).centroid
    near = _near_presses(cm, np.array([[0.0, 0.0]]), 1.5)
    centre = np.unravel_index(np.argmin(np.hypot(cm.x0_mm + cm.step_mm * np.arange(cm.n)[None, :],
                                                 cm.y0_mm + cm.step_mm * np.arange(cm.n)[:, None])), near.shape)
    assert near[centre] and near.sum() < 0.05 * near.size


def test_the_width_check_needs_three_presses_a_diameter_and_reads_the_evaluated_widths(calibrated, tmp_path):
    """Issue 26: a width model is judged by its held-out error at calibration, the presses of its rarest
    diameter (the learning curve settles at 3) and, on a recording of circles, the error measured there."""
    from dataclasses import replace as dc_replace

    from optitac_edge.calibration.steps import calibrate_width
    from optitac_edge.calibration.verdict import width_check

    _, fibers, _, _ = calibrated
    widths = Recording(write_scenario(tmp_path / "widths", "widths", seed=4))
    bundle, summary = calibrate_width(widths, fibers)
    assert summary["presses_per_diameter"] == 5 and len(summary["heldout_rmse_mm"]) == 2
    check = width_check(bundle)
    assert check is not None and check.ok and "5 presses of its rarest diameter (need 3)" in check.seen
    other = Recording(write_scenario(tmp_path / "widths2", "widths", seed=5, day=2))
    here = width_check(bundle, measure_recording(other, bundle, progress=False), other.truth)
    assert here is not None and here.ok and "mm here over" in here.seen
    few = bundle.with_updates(extra_meta={**bundle.extra_meta,
                                          "width_fit": {**bundle.extra_meta["width_fit"], "presses_per_diameter": 2}})
    assert not width_check(few).ok
    old = bundle.with_updates(extra_meta={**bundle.extra_meta, "width_fit": {"frames": 120, "kind": "monotone"}})
    assert "older calibration" in width_check(old).seen
    assert dc_replace(check, ok=False).line().startswith("  [FAIL] width:")
