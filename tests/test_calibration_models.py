"""Centroid error maps and the width model: the mathematics, on analytic cases."""

from __future__ import annotations

import numpy as np
import pytest

from optitac_edge.calibration.centroid_fit import fit_centroid_map
from optitac_edge.calibration.width_fit import fit_axis, fit_monotone_axis, fit_width_model
from optitac_edge.core.centroid_map import CentroidErrorMap
from optitac_edge.core.layout import hex_layout
from optitac_edge.core.width_model import AxisMap, WidthModel


def test_constant_error_is_removed_everywhere():
    true = hex_layout().xy_mm
    measured = true + np.array([0.3, -0.2])
    cm = fit_centroid_map(measured, true, half_span_mm=15.0, cells=300, sigma_cells=3)
    for x, y in [(0, 0), (5.3, -2.1), (-11, 9), (14, 14)]:
        cx, cy = cm.correct(x + 0.3, y - 0.2)
        assert cx == pytest.approx(x, abs=1e-5) and cy == pytest.approx(y, abs=1e-5)


@pytest.mark.parametrize("fill", ["nearest", "linear"])
def test_smooth_error_field_is_learned_between_presses(fill):
    """A radial pull towards the centre (as at the rim) is corrected at unseen positions."""
    true = hex_layout().xy_mm

    def pull(p):
        return -0.04 * p * (np.linalg.norm(p, axis=-1, keepdims=True) / 12.0)
    measured = true + pull(true)
    cm = fit_centroid_map(measured, true, half_span_mm=15.0, fill=fill)  # 1000 cells, sigma 10
    rng = np.random.default_rng(0)
    unseen = rng.uniform(-8, 8, (200, 2))
    meas_unseen = unseen + pull(unseen)
    corrected = np.array([cm.correct(x, y) for x, y in meas_unseen])
    raw = np.sqrt(np.mean((meas_unseen - unseen) ** 2))
    after = np.sqrt(np.mean((corrected - unseen) ** 2))
    assert after < (0.35 if fill == "nearest" else 0.1) * raw


def test_map_geometry_and_nearest_cell_lookup():
    cm = fit_centroid_map(np.array([[0, 0], [1, 0], [0, 1.0]]), np.zeros((3, 2)), half_span_mm=2.0, cells=5,
                          sigma_cells=0.0)
    assert cm.step_mm == pytest.approx(1.0) and cm.x0_mm == -2.0 and cm.n == 5
    # outside the mesh the border cell is used, never an index error
    assert np.isfinite(cm.correct(100.0, -100.0)).all()


def test_bundle_round_trip_of_the_map():
    cm = fit_centroid_map(np.array([[0, 0], [1, 0], [0, 1.0]]), np.zeros((3, 2)), half_span_mm=2.0, cells=9)
    meta, arrays = cm.to_bundle()
    back = CentroidErrorMap.from_bundle(meta, arrays)
    assert back.correct(0.7, 0.2) == cm.correct(0.7, 0.2)


def test_too_few_presses_is_an_error():
    with pytest.raises(ValueError):
        fit_centroid_map(np.zeros((2, 2)), np.zeros((2, 2)), half_span_mm=1.0)


def test_linear_width_model_inverts_a_linear_response():
    true = np.linspace(1.85, 20.09, 12)
    major = 3.43 + true / 2.35  # the paper's fitted numbers as a forward model
    minor = 2.47 + true / 2.51
    model = fit_width_model(major, minor, true, kind="linear")
    assert fit_axis(major, true) == pytest.approx((3.43, 2.35))
    assert fit_axis(minor, true) == pytest.approx((2.47, 2.51))
    for t, a, b in zip(true, major, minor):
        assert model.correct(a, b) == pytest.approx((t, t))
    assert model.correct(3.43 + 30 / 2.35, 0.0)[0] == pytest.approx(30.0)  # extrapolated beyond the knots
    back = WidthModel.from_bundle(model.to_bundle())
    assert back.correct(7.0, 6.0) == model.correct(7.0, 6.0)


def test_monotone_width_model_follows_a_curved_response():
    true = np.repeat(np.linspace(1.85, 20.09, 12), 3)
    measured = 2.5 + 4.0 * np.tanh(true / 12.0) + 0.1 * true  # saturating, like the skin
    model = fit_width_model(measured, measured, true, kind="monotone")
    lin = fit_width_model(measured, measured, true, kind="linear")
    probe = np.linspace(2.0, 19.5, 40)
    response = 2.5 + 4.0 * np.tanh(probe / 12.0) + 0.1 * probe
    mono_err = np.abs([model.correct(r, r)[0] - t for r, t in zip(response, probe)]).max()
    lin_err = np.abs([lin.correct(r, r)[0] - t for r, t in zip(response, probe)]).max()
    assert mono_err < 0.1 < lin_err


def test_monotone_fit_pools_non_increasing_means():
    axis = fit_monotone_axis(np.array([3.0, 2.9, 4.0]), np.array([2.0, 3.0, 5.0]))
    assert np.all(np.diff(axis.knots_measured) > 0) and axis.knots_measured.size == 2
    assert axis(axis.knots_measured[0]) == pytest.approx(2.5)


def test_width_fit_needs_two_sizes_and_clips_at_zero():
    with pytest.raises(ValueError):
        fit_axis(np.array([5.0, 5.0]), np.array([3.0, 3.0]))
    with pytest.raises(ValueError):
        fit_width_model(np.array([5.0, 5.1]), np.array([5.0, 5.1]), np.array([3.0, 3.0]))
    model = WidthModel("linear", AxisMap.linear(3.0, 2.0), AxisMap.linear(3.0, 2.0))
    assert model.correct(1.0, 2.0) == (0.0, 0.0)
