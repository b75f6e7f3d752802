"""Depth and force: the simulator's force model, the truth's force column, the fit, the runtime model, the CLI."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optitac_edge.calibration.depth_fit import fit_radial_monotone
from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.depth_model import DepthForceModel, RadialMonotoneMap
from optitac_edge.core.width_model import AxisMap
from optitac_edge.errors import RecordingError
from optitac_edge.io.recording import FORCE_COLUMN, TRUTH_HEADER, Recording, read_truth
from optitac_edge.sim.skin import DEFAULT_SKIN, Indenter, SkinModel, contact_force_n, footprint_area_mm2

# -- the simulator's force model -------------------------------------------------------------


def test_force_is_the_flat_punch_law_at_the_centre_and_stiffens_with_depth_and_towards_the_rim():
    skin = SkinModel(modulus_mpa=0.1, stiffening_mm=4.0, rim_stiffening=1.0)
    circle = Indenter("circle", 0.0, 0.0, 0.0, 5.0, 1.0)
    a = 2.5  # the circle's radius
    assert contact_force_n(circle, 12.0, skin) == pytest.approx(2 * 0.1 * a * 1.0 * (1 + 1 / 4))
    deep = Indenter("circle", 0.0, 0.0, 0.0, 5.0, 4.0)  # at the stiffening depth the stiffness doubles
    assert contact_force_n(deep, 12.0, skin) / 4.0 == pytest.approx(2 * 2 * 0.1 * a)
    rim = Indenter("circle", 12.0, 0.0, 0.0, 5.0, 1.0)  # at the clamp radius: twice as stiff
    assert contact_force_n(rim, 12.0, skin) == pytest.approx(2 * contact_force_n(circle, 12.0, skin))
    assert contact_force_n(Indenter("circle", 0.0, 0.0, 0.0, 5.0, 0.0), 12.0, skin) == 0.0


@pytest.mark.parametrize("shape, area", [("circle", math.pi * 4), ("square", 16.0),
                                         ("triangle", math.sqrt(3) * 4), ("edge", 4 * 12.0),
                                         ("ellipse", math.pi * 4 * 0.6)])
def test_footprint_areas(shape, area):
    assert footprint_area_mm2(Indenter(shape, 0.0, 0.0, 0.0, 4.0, 1.0), DEFAULT_SKIN) == pytest.approx(area)


# -- truth.csv's force column ----------------------------------------------------------------


def _truth_file(tmp_path, header, rows):
    path = tmp_path / "truth.csv"
    path.write_text("\n".join([",".join(header), *rows]) + "\n")
    return path


def test_the_force_column_is_read_and_optional(tmp_path):
    row = "0,1,circle,0,0,0,5,1.5,{}"
    t = read_truth(_truth_file(tmp_path, TRUTH_HEADER + (FORCE_COLUMN,), [row.format("1.25"), "1,0,,,,,,,"]), 2)
    assert t.force_n is not None and t.force_n[0] == 1.25 and math.isnan(t.force_n[1])
    assert read_truth(_truth_file(tmp_path, TRUTH_HEADER, ["0,1,circle,0,0,0,5,1.5"]), 1).force_n is None


@pytest.mark.parametrize("value", ["-1", "inf", "x"])
def test_a_bad_force_is_refused_in_one_line_naming_file_and_line(tmp_path, value):
    path = _truth_file(tmp_path, TRUTH_HEADER + (FORCE_COLUMN,), [f"0,1,circle,0,0,0,5,1.5,{value}"])
    with pytest.raises(RecordingError, match=r"truth.csv: line 2") as err:
        read_truth(path, 1)
    assert "\n" not in str(err.value)


# -- the fit and the runtime model -----------------------------------------------------------


def test_the_fit_recovers_a_known_radial_gain_and_curve():
    """Presses at 6 depths and 5 radii whose strength follows depth = g(s * (1 + 0.5 rho^2)) exactly."""
    rng = np.random.default_rng(1)
    depths = np.repeat([0.5, 1.0, 1.5, 2.0, 3.0, 4.0], 5)
    rho2 = np.tile([0.0, 0.1, 0.2, 0.3, 0.4], 6)
    scaled = 10.0 * depths ** 1.5  # g^-1
    strength = scaled / (1.0 + 0.5 * rho2)
    fit = fit_radial_monotone(strength, rho2, depths, 12.0, level=depths, weight=rng.integers(1, 4, depths.size))
    assert fit.model.radial == pytest.approx(0.5, abs=1e-9) and fit.rmse < 1e-9
    m = fit.model
    assert m(float(strength[7]), math.sqrt(float(rho2[7])) * 12.0, 0.0) == pytest.approx(depths[7])


def test_a_rim_that_stiffens_late_is_fitted_with_a_higher_power_where_the_presses_tell():
    """A wide array's rim stiffens the skin only near it: depth = g(s * (1 + 0.8 rho^8)). Presses at the
    centre and two rings (the depths experiment on 1027 fibers) recover it; at the centre and one ring
    a power cannot be told from a gain, and the quadratic stays."""
    depths = np.repeat([0.5, 1.0, 1.5, 2.0, 3.0, 4.0], 3)
    rho2 = np.tile([0.0, 0.25, 0.79], 6)
    strength = 10.0 * depths ** 1.5 / (1.0 + 0.8 * rho2 ** 4)
    fit = fit_radial_monotone(strength, rho2, depths, 27.0, level=depths)
    assert (fit.model.power, fit.model.radial) == (4, pytest.approx(0.8)) and fit.rmse < 1e-9
    two = rho2 < 0.5
    fit = fit_radial_monotone(strength[two], rho2[two], depths[two], 27.0, level=depths[two])
    assert fit.model.power == 1
    m = RadialMonotoneMap(0.8, 10.0, AxisMap(np.array([1.0, 2.0]), np.array([1.0, 2.0])), power=4)
    assert m.scaled(1.0, 5.0, 0.0) == pytest.approx(1.0 + 0.8 * 0.25 ** 4)
    assert RadialMonotoneMap.from_dict({k: v for k, v in m.to_dict().items() if k != "power"}).power == 1
    assert RadialMonotoneMap.from_dict(m.to_dict()).power == 4
    for bad in (0, 5, 2.0, True):
        with pytest.raises(ValueError, match="radial power"):
            RadialMonotoneMap.from_dict({**m.to_dict(), "power": bad})


def test_the_fit_refuses_presses_at_fewer_than_three_depths():
    with pytest.raises(ValueError, match="3 depths"):
        fit_radial_monotone(np.array([1.0, 2.0, 3.0]), np.zeros(3), np.array([1.0, 2.0, 2.0]), 12.0,
                            level=np.array([1.0, 2.0, 2.0]))


def _model(force: bool = True) -> DepthForceModel:
    curve = AxisMap(np.array([10.0, 20.0, 40.0]), np.array([1.0, 2.0, 3.0]))
    fcurve = AxisMap(np.array([10.0, 40.0]), np.array([0.5, 5.0]))
    return DepthForceModel("strength", RadialMonotoneMap(1.0, 10.0, curve),
                           RadialMonotoneMap(0.0, 10.0, fcurve) if force else None)


def test_the_model_scales_by_the_radius_caps_it_at_the_rim_and_extends_linearly():
    m = _model()
    est = ContactEstimate(contact=True, x_mm=0.0, y_mm=0.0, strength=15.0)
    m.apply(est)
    assert est.depth_mm == pytest.approx(1.5) and est.force_n == pytest.approx(0.5 + 4.5 * 5 / 30)
    est.x_mm, est.y_mm = 6.0, 8.0  # r = 10 mm, rho = 1: strength x 2
    m.apply(est)
    assert est.depth_mm == pytest.approx(2.5)
    est.x_mm = 60.0  # beyond the rim: the factor stays at its rim value
    m.apply(est)
    assert est.depth_mm == pytest.approx(np.interp(15.0 * 2, [10, 20, 40], [1, 2, 3]))
    est.x_mm, est.y_mm, est.strength = 0.0, 0.0, 60.0  # beyond the last knot: the last segment's slope
    m.apply(est)
    assert est.depth_mm == pytest.approx(3.0 + 20 / 20 * 1.0)
    est.x_mm = math.nan
    m.apply(est)
    assert math.isnan(est.depth_mm) and math.isnan(est.force_n)
    no_force = _model(force=False)
    est.x_mm = 0.0
    no_force.apply(est)
    assert est.depth_mm == pytest.approx(4.0) and math.isnan(est.force_n)


def test_the_model_round_trips_and_refuses_bad_parameters():
    m = _model()
    again = DepthForceModel.from_bundle(m.to_bundle())
    assert again.to_bundle() == m.to_bundle()
    bad = m.to_bundle()
    bad["depth"]["knots_target"] = [3.0, 2.0, 1.0]
    with pytest.raises(ValueError, match="must not decrease"):
        DepthForceModel.from_bundle(bad)
    with pytest.raises(ValueError, match="radial"):
        RadialMonotoneMap(-1.0, 10.0, m.depth.curve)
    with pytest.raises(ValueError, match="unknown depth feature"):
        DepthForceModel("area_mm2", m.depth)


# -- the calibration step, end to end on the simulator ---------------------------------------


def test_calibrate_depth_on_another_day_meets_the_depth_and_force_targets(tmp_path, bundle_path, capsys):
    """Issue 16: calibrated on one day's ``depths`` presses, evaluated on another day's: depth RMSE against the
    simulator's real depths <= 0.10 mm over 0.5-4 mm, force RMSE <= 5 % of the range; the CSV carries both."""
    import json
    import shutil

    from optitac_edge.calibration.evaluation import depth_accuracy, read_contacts_csv
    from optitac_edge.calibration.measure import measure_recording
    from optitac_edge.cli import main
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.recording import Recording

    cal = tmp_path / "cal.npz"
    shutil.copy(bundle_path, cal)
    assert main(["sim", str(tmp_path / "d1"), "--scenario", "depths", "--seed", "105", "--day", "1", "-q"]) == 0
    assert main(["sim", str(tmp_path / "d2"), "--scenario", "depths", "--seed", "205", "--day", "2", "-q"]) == 0
    assert main(["calibrate", "depth", str(tmp_path / "d1"), "--cal", str(cal)]) == 0
    out = capsys.readouterr().out
    assert "with the depth calibration: presses 112" in out and "response drift prior 5%" in out
    rec = Recording(tmp_path / "d2")
    real = dict(json.loads((tmp_path / "d2" / "meta.json").read_text())["simulator"]["real_depth_mm"])
    starts = sorted(real)
    first = np.searchsorted(starts, rec.truth.frame, side="right") - 1
    real_depth = np.array([real[starts[k]] for k in first])
    m = measure_recording(rec, load_bundle(cal), progress=False)
    report = depth_accuracy(m, rec.truth, real_depth)
    assert report is not None and report.n == 224
    assert report.depth_rmse_mm <= 0.10 and report.force_rmse_pct <= 5.0
    assert main(["evaluate", str(tmp_path / "d2"), "--cal", str(cal)]) == 0
    assert "force RMSE" in capsys.readouterr().out
    assert main(["replay", str(tmp_path / "d2"), "--cal", str(cal), "-o", str(tmp_path / "c.csv"), "-q"]) == 0
    back = read_contacts_csv(tmp_path / "c.csv")
    assert back.depth_mm is not None and np.nanmax(np.abs(back.depth_mm - m.depth_mm)) < 1e-4
    # issue 37: two days' presses, each with its own baseline, are held out day by day (no prior)
    both = tmp_path / "both.npz"
    shutil.copy(bundle_path, both)
    assert main(["calibrate", "depth", str(tmp_path / "d1"), str(tmp_path / "d2"), "--cal", str(both)]) == 0
    assert "presses 224" in (out := capsys.readouterr().out) and "heldout by 2 sessions" in out
    assert load_bundle(both).extra_meta["depth_fit"]["folds_by"] == "session"


def test_calibrate_depth_refuses_presses_at_one_depth(tmp_path, bundle_path, capsys):
    import shutil

    from optitac_edge.cli import main

    cal = tmp_path / "cal.npz"
    shutil.copy(bundle_path, cal)
    assert main(["sim", str(tmp_path / "r"), "--scenario", "repeat", "--seed", "1", "--frames", "40", "-q"]) == 0
    assert main(["calibrate", "depth", str(tmp_path / "r"), "--cal", str(cal)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "3 depths or more" in err[0]


def test_the_width_feature_is_the_mean_raw_fwhm_and_the_model_runs_before_the_width_model(bundle_path):
    from optitac_edge.calibration.bundle_models import with_depth_model, with_width_model
    from optitac_edge.core.corrections import ContactCorrector
    from optitac_edge.core.depth_model import depth_feature
    from optitac_edge.core.width_model import WidthModel
    from optitac_edge.io.bundle_file import load_bundle

    est = ContactEstimate(contact=True, x_mm=0.0, y_mm=0.0, major_mm=6.0, minor_mm=4.0, strength=99.0)
    assert depth_feature(est, "width") == 5.0 and depth_feature(est, "strength") == 99.0
    curve = AxisMap(np.array([4.0, 6.0]), np.array([1.0, 3.0]))
    model = DepthForceModel("width", RadialMonotoneMap(0.0, 10.0, curve))
    model.apply(est)
    assert est.depth_mm == pytest.approx(2.0)
    double = AxisMap(np.array([0.0, 10.0]), np.array([0.0, 20.0]))  # a width model that doubles every width
    bundle = with_depth_model(with_width_model(load_bundle(bundle_path), WidthModel("monotone", double, double)),
                              model)
    est = ContactEstimate(contact=True, x_mm=0.0, y_mm=0.0, major_mm=6.0, minor_mm=4.0)
    ContactCorrector(bundle).apply(est)
    assert est.depth_mm == pytest.approx(2.0) and (est.major_mm, est.minor_mm) == (12.0, 8.0)


@pytest.mark.parametrize("rings, points", [(8, 7), (18, 13)])
def test_the_simulated_depths_scenario_presses_where_and_as_deep_as_the_rig_experiment(rings, points):
    """The simulator's ``depths`` scenario mirrors the bring-up experiment of that name (the simulator sits
    below bring-up and keeps its own copy): the same indenter, points and depths, twice each; the paper's
    array at the centre and half its radius out, 1027 fibers at 13.5 and 24 mm too."""
    from collections import Counter

    from optitac_edge.bringup.experiments import plan
    from optitac_edge.core.layout import hex_layout
    from optitac_edge.sim.scenarios import schedule

    layout = hex_layout(rings)
    frames = schedule("depths", seed=3, layout=layout)
    sim = [p for k, p in enumerate(frames) if p is not None and p is not frames[k - 1]]
    rig = plan("depths", layout, seed=3)

    def key(shape: str, size: float, x: float, y: float, d: float) -> tuple:
        return shape, size, round(x, 9), round(y, 9), d

    assert Counter(key(p.shape, p.size_mm, p.x_mm, p.y_mm, p.depth_mm) for p in sim) == \
        Counter(key(p.shape, p.size_mm, p.x_mm, p.y_mm, p.depth_mm) for p in rig)
    assert len(sim) == points * 8 * 2


def test_collect_calibrate_and_evaluate_depth_without_a_load_cell(tmp_path, capsys):
    """Issue 26: the normal case, a rig without a load cell. collect depths on sim:// (no force_n column),
    calibrate depth on it (it chose its input on held-out presses), evaluate on another day's collection:
    the verdict's depth check passes with the held-out figure beside the measured one. (A 12-press collection
    once ended in a traceback: the report's per-press array held the missing forces as NaN.)"""
    from optitac_edge.cli import main

    rec, other, cal = tmp_path / "depths", tmp_path / "day2", tmp_path / "cal.npz"
    assert main(["collect", "depths", "--rig", "sim://", "-o", str(rec), "--limit", "56"]) == 0
    # issue 38: enough presses are said to be enough (it read "needs 56 presses" after collecting them)
    line = capsys.readouterr().out.splitlines()[-1]
    assert line.startswith("56 presses collected: enough for the depth model (it needs 56 presses") and "too few" not in line
    assert main(["collect", "depths", "--rig", "sim://?day=2", "--seed", "5", "-o", str(other),
                 "--limit", "28"]) == 0  # evaluated on half as many: the check reads the bundle's held-out figure
    assert Recording(rec).truth.force_n is None
    assert main(["calibrate", "fibers", str(rec), "-o", str(cal)]) == 0
    capsys.readouterr()
    assert main(["calibrate", "depth", str(rec), "--cal", str(cal)]) == 0
    out = capsys.readouterr().out
    assert "with the depth calibration" in out and "heldout depth rmse mm" in out and "force" not in out
    assert main(["evaluate", str(other), "--cal", str(cal)]) == 0
    out = capsys.readouterr().out
    depth_line = next(line for line in out.splitlines() if "] depth:" in line)
    assert depth_line.startswith("  [ok] depth:") and "held-out RMSE" in depth_line and "here over" in depth_line
    assert "force" not in out


def test_a_depth_model_from_too_few_presses_is_refused_by_the_verdict(tmp_path, capsys):
    from optitac_edge.cli import main

    rec, cal = tmp_path / "depths", tmp_path / "cal.npz"
    assert main(["collect", "depths", "--rig", "sim://", "-o", str(rec), "--limit", "12"]) == 0
    assert "12 presses collected: too few for the depth model (it needs 56 presses" in capsys.readouterr().out
    assert main(["calibrate", "fibers", str(rec), "-o", str(cal)]) == 0
    assert main(["calibrate", "depth", str(rec), "--cal", str(cal)]) == 0
    capsys.readouterr()
    assert main(["evaluate", str(rec), "--cal", str(cal), "--strict"]) == 1
    out = capsys.readouterr().out
    assert "[FAIL] depth: 17 presses (need 56)" in out
    # the report: the depth model's choice and held-out figures (no raw dicts), and the check from the bundle
    assert main(["report", str(cal), "-o", str(tmp_path / "rep")]) == 0
    text = (tmp_path / "rep" / "index.md").read_text()
    assert "{" not in text and "}" not in text
    assert "Depth calibration, depth candidates on held-out presses (score): width " in text
    assert "[FAIL] depth: 17 presses (need 56)" in text


def test_the_depth_curve_is_sklearns_weighted_isotonic_regression_of_the_levels_means() -> None:
    """The curve's knots: each level's weighted mean (feature, depth), equal features pooled, the depths made
    non-decreasing by a weighted isotonic regression -- the same knots as scikit-learn's IsotonicRegression
    (the fit it replaced: scipy's function without per-call validation, the fit runs ~10 000 times a
    calibration), ties and features equal to rounding included."""
    from sklearn.isotonic import IsotonicRegression

    from optitac_edge.calibration.depth_fit import _curve, grouped_means

    rng = np.random.default_rng(0)
    for trial in range(60):
        n = int(rng.integers(3, 40))
        feature = np.round(rng.uniform(0.0, 5.0, n), 1 if trial % 2 else 6)  # many ties, or none
        depth = 0.7 * feature + rng.normal(0.0, 0.5, n)
        level = rng.integers(0, 8, n).astype(float) if trial % 3 else np.arange(n, dtype=float)
        weight = rng.uniform(0.5, 3.0, n)
        curve = _curve(feature, depth, weight, level)
        means, w = grouped_means(np.stack([feature, depth], axis=1), level, weight)
        order = np.argsort(means[:, 0], kind="stable")
        x, y, w = means[order, 0], means[order, 1], w[order]
        first = np.concatenate([[True], ~np.isclose(np.diff(x), 0.0, rtol=0.0, atol=1e-12)])
        if first.sum() < 2:
            assert curve is None
            continue
        expected = IsotonicRegression(increasing=True).fit(x, y, sample_weight=w).predict(x)[first]
        assert curve is not None
        np.testing.assert_allclose(curve.knots_measured, x[first])
        np.testing.assert_allclose(curve.knots_true, np.maximum.accumulate(expected), atol=1e-12)
