"""Issue 26: the width model's form and the centroid map's fill are chosen by presses held out of the fit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optitac_edge.calibration.centroid_fit import held_out_fills
from optitac_edge.calibration.width_fit import fit_width_form, select_width_form
from optitac_edge.core.width_model import AxisMap, WidthModel

DIAMETERS = np.array([2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0, 14.0, 16.0])


def _circles(gain: float, seed: int = 0) -> tuple[np.ndarray, ...]:
    """Circles whose measured widths follow 3 + 0.5 D, read (1 + gain rho^2) times narrower further out."""
    rng = np.random.default_rng(seed)
    true = np.repeat(DIAMETERS, 6)
    rho2 = rng.uniform(0.0, 0.6, true.size)
    clean = 3.0 + 0.5 * true
    major = clean * (1 + 0.01 * rng.standard_normal(true.size))
    minor = clean / (1.0 + gain * rho2) * (1 + 0.01 * rng.standard_normal(true.size))
    return major, minor, rho2, true, np.arange(true.size)


def test_a_width_squeezed_towards_the_rim_chooses_a_radial_form_and_recovers_its_gain():
    major, minor, rho2, true, groups = _circles(gain=0.3)
    form, model, candidates = select_width_form(major, minor, rho2, true, groups, 12.0)
    assert form.endswith("-radial")
    assert model.radial_minor == pytest.approx(0.3, abs=0.05) and abs(model.radial_major) <= 0.05
    scores = {c["form"]: c["score_mm"] for c in candidates}
    assert scores[form] == min(scores.values()) and scores["monotone"] > 2 * scores[form]


def test_without_a_radial_effect_the_plain_form_is_as_good():
    major, minor, rho2, true, groups = _circles(gain=0.0)
    _, _, candidates = select_width_form(major, minor, rho2, true, groups, 12.0)
    scores = {c["form"]: c["score_mm"] for c in candidates}
    assert scores["monotone"] <= 1.1 * scores["monotone-radial"]


def test_the_radial_width_model_scales_by_the_position_and_round_trips():
    m = WidthModel("linear", AxisMap.linear(0.0, 1.0), AxisMap.linear(0.0, 1.0), 0.5, 1.0, 10.0)
    assert m.correct(4.0, 2.0, 0.0, 0.0) == pytest.approx((4.0, 2.0))
    assert m.correct(4.0, 2.0, 6.0, 8.0) == pytest.approx((6.0, 4.0))  # rho = 1
    assert m.correct(4.0, 2.0, 60.0, 0.0) == pytest.approx((6.0, 4.0))  # capped at the rim
    assert m.correct(4.0, 2.0, math.nan, 0.0) == pytest.approx((4.0, 2.0))
    again = WidthModel.from_bundle(m.to_bundle())
    assert again.to_bundle() == m.to_bundle()
    old = {k: v for k, v in m.to_bundle().items() if k not in ("radial_major", "radial_minor", "radius_mm")}
    assert WidthModel.from_bundle(old).correct(4.0, 2.0, 6.0, 8.0) == pytest.approx((4.0, 2.0))
    with pytest.raises(ValueError, match="radial gains"):
        WidthModel("linear", m.major, m.minor, -1.0)


def test_every_width_form_fits():
    major, minor, rho2, true, _ = _circles(gain=0.2)
    for form in ("linear", "monotone", "linear-radial", "monotone-radial"):
        assert fit_width_form(form, major, minor, rho2, true, 12.0).kind == form.split("-")[0]
    with pytest.raises(ValueError, match="unknown width model form"):
        fit_width_form("cubic", major, minor, rho2, true, 12.0)


def test_a_smooth_error_field_is_followed_better_by_the_linear_fill_between_presses():
    """Presses on a 1.5 mm grid whose error grows linearly with position: a held-out press is predicted from
    its neighbours far better by linear interpolation than by the nearest neighbour's error."""
    g = np.arange(-9.0, 9.01, 1.5)
    true = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    measured = true + 0.05 * true  # 5 % too far out
    out = {c["fill"]: c for c in held_out_fills(measured, true, np.arange(len(true)), 12.0)}
    assert out["linear"]["score_mm"] < 0.8 * out["nearest"]["score_mm"]
    assert all(len(c["heldout_rmse_mm"]) == 2 and c["heldout_spread_mm"] >= 0 for c in out.values())


def test_no_map_is_adopted_where_held_out_presses_show_none_helps():
    """Presses whose error is noise about the truth (no field a map could learn, as a few presses of a sparse,
    noisy sensor gave): a map fitted to some presses misplaces the others, the raw estimate ('none') wins, and
    calibrate centroid would keep it; where the error is a field, a map wins by far."""
    rng = np.random.default_rng(4)
    true = rng.uniform(-12.0, 12.0, (14, 2))
    noisy = true + rng.normal(0.0, 3.0, true.shape)
    out = {c["fill"]: c for c in held_out_fills(noisy, true, np.arange(len(true)), 16.0)}
    assert min(out, key=lambda f: out[f]["score_mm"]) == "none"
    field = true + 0.2 * true  # 20 % too far out: a map learns it
    out = {c["fill"]: c for c in held_out_fills(field, true, np.arange(len(true)), 16.0)}
    assert out["none"]["score_mm"] > 2 * min(c["score_mm"] for c in out.values())
    from optitac_edge.calibration.centroid_fit import fit_centroid_map

    zero = fit_centroid_map(noisy, true, 16.0, fill="none")
    assert zero.correct(3.0, -4.0) == (3.0, -4.0)


def test_a_map_must_beat_the_raw_estimate_by_more_than_the_presses_scatter():
    """The one-standard-error rule: a map whose held-out score is a little better than no map's by chance
    (13 noisy presses of a sparse sensor: the real data set's nearest fill scored 2.76 mm against 2.89 mm
    and misplaced the next day's presses) is not adopted; a map that learns a real field is."""
    from optitac_edge.calibration.centroid_fit import choose_fill

    by_score = []
    for seed in range(16):
        rng = np.random.default_rng(seed)
        true = rng.uniform(-12.0, 12.0, (13, 2))
        chosen, candidates = choose_fill(true + rng.normal(0.0, 3.0, true.shape), true, np.arange(13), 16.0,
                                         ("nearest", "none"))
        assert chosen["fill"] == "none", seed
        by_score.append(min(candidates, key=lambda c: c["score_mm"])["fill"])
    assert set(by_score) != {"none"}  # some draws score a map better by chance: the rule keeps them out
    true = np.random.default_rng(99).uniform(-12.0, 12.0, (13, 2))
    chosen, _ = choose_fill(true + 0.2 * true, true, np.arange(13), 16.0)
    assert chosen["fill"] != "none" and chosen["gain_mm2"] > chosen["gain_se_mm2"] > 0
