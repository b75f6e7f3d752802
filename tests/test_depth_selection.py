"""Issue 26: the depth/force input is chosen by presses held out of the fit, with a guard against the skin's
response drifting between days (pure functions on synthetic presses with known answers)."""

from __future__ import annotations

import numpy as np
import pytest

from optitac_edge.calibration.depth_fit import MIN_SELECTION_PRESSES, Presses, held_out, select_feature
from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.depth_model import DEPTH_FEATURES, GAIN_EXPONENT, depth_feature

LEVELS = np.array([0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0])


def _presses(reps: int = 7, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    depth = np.repeat(LEVELS, reps)
    rho2 = np.tile(np.linspace(0.0, 0.5, reps), LEVELS.size)
    return depth, rho2, rng


def _presses_at(rho2: np.ndarray, depth: np.ndarray, session: np.ndarray | None = None) -> Presses:
    """Presses at ``depth`` (their level and target), one frame each, each its own group."""
    return Presses(rho2, depth, depth, np.ones_like(depth), np.arange(depth.size), session)


def test_an_uninformative_feature_loses_to_an_informative_one():
    """Width that does not grow with depth (a skin that drapes tightly) against a strength that does."""
    depth, rho2, rng = _presses()
    features = {"width": 5.0 + 0.05 * rng.standard_normal(depth.size),
                "strength": 20.0 * depth ** 1.3 * (1 + 0.01 * rng.standard_normal(depth.size))}
    sel = select_feature(features, _presses_at(rho2, depth), 12.0)
    assert sel.feature == "strength"
    by = {c.feature: c for c in sel.candidates}
    assert by["width"].heldout_rmse > 0.5 and by["strength"].heldout_rmse < 0.05
    assert sel.folds == 8 and sel.chosen is by["strength"]


def test_equally_informative_features_the_one_the_skins_drift_cannot_move_wins():
    """Both follow depth exactly; strength moves with the skin's response (exponent 1), fullness does not."""
    depth, rho2, _ = _presses()
    features = {"strength": 20.0 * depth ** 1.3, "fullness": 10.0 + 4.0 * depth}
    sel = select_feature(features, _presses_at(rho2, depth), 12.0)
    assert sel.feature == "fullness"
    by = {c.feature: c for c in sel.candidates}
    assert by["fullness"].drift_rmse == pytest.approx(0.0, abs=1e-12)
    # strength x 1.05: a power law depth = (s/20)^(1/1.3) moves by ~ depth * 0.05 / 1.3
    assert by["strength"].drift_rmse == pytest.approx(np.sqrt(np.mean(depth ** 2)) * 0.05 / 1.3, rel=0.1)
    no_drift = select_feature(features, _presses_at(rho2, depth), 12.0, drift=0.0)
    assert {c.feature: c.drift_rmse for c in no_drift.candidates}["strength"] == 0.0


def test_the_held_out_error_measures_the_noise_of_presses_the_fit_never_saw():
    """Depth = feature exactly, plus press noise of 0.1 mm on the target: the held-out RMSE is ~0.1 mm
    while the fit's own error is smaller (it partly fits the noise)."""
    depth, rho2, rng = _presses(reps=14)
    noisy = depth + 0.1 * rng.standard_normal(depth.size)
    c = held_out(depth * 3.0, Presses(rho2 * 0.0, noisy, depth, np.ones_like(depth), np.arange(depth.size)), 12.0,
                 exponent=0.0)
    assert 0.08 < c.heldout_rmse < 0.13 and 0.0 < c.heldout_spread < 0.05


@pytest.mark.parametrize("sizes", [[3] * 16, [1, 2, 3, 4, 5, 6, 7, 8, 9, 10], [2] * 5 + [7] * 3])
def test_folds_never_split_a_press_and_balance_as_group_k_fold_does(sizes):
    """Every row held out exactly once, a press never on both sides, fold sizes as scikit-learn's GroupKFold."""
    from sklearn.model_selection import GroupKFold

    from optitac_edge.calibration.folds import press_folds

    groups = np.repeat(np.arange(len(sizes)) * 7 + 3, sizes)  # labels need not be 0..n-1
    folds = list(press_folds(groups, 4))
    held = np.concatenate([test for _, test in folds])
    assert np.array_equal(np.sort(held), np.arange(groups.size))
    for train, test in folds:
        assert not set(groups[train]) & set(groups[test])
        assert np.array_equal(np.sort(np.concatenate([train, test])), np.arange(groups.size))
    theirs = sorted(len(test) for _, test in GroupKFold(n_splits=4).split(groups, groups=groups))
    assert sorted(len(test) for _, test in folds) == theirs
    with pytest.raises(ValueError, match="folds"):
        next(press_folds(groups, len(sizes) + 1))


def test_too_few_presses_are_refused_in_one_line():
    depth = LEVELS[: MIN_SELECTION_PRESSES - 1]
    with pytest.raises(ValueError, match=f"need {MIN_SELECTION_PRESSES} presses or more"):
        select_feature({"width": depth}, _presses_at(depth * 0, depth), 12.0)


def test_every_candidate_is_a_feature_of_a_contact_and_scales_as_declared():
    """Each feature of a contact, and its declared response to a gain g on the darkening (strength, peak
    x g; widths and peak-relative ratios unchanged)."""
    est = ContactEstimate(contact=True, major_mm=6.0, minor_mm=4.0, strength=80.0, peak=0.5, area_mm2=20.0)
    values = {f: depth_feature(est, f) for f in DEPTH_FEATURES}
    assert values == pytest.approx({"width": 5.0, "strength": 80.0, "peak": 0.5, "area": 20.0, "fullness": 160.0,
                                    "strength_width": 400.0, "root_strength_width": np.sqrt(80.0) * 5.0,
                                    "fullness_width": 800.0})
    g = 1.1
    gained = ContactEstimate(contact=True, major_mm=6.0, minor_mm=4.0, strength=80.0 * g, peak=0.5 * g,
                             area_mm2=20.0)
    for f in DEPTH_FEATURES:
        assert depth_feature(gained, f) == pytest.approx(values[f] * g ** GAIN_EXPONENT[f]), f


def _two_sessions(change: float) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """Presses on two days: strength follows depth exactly but the second day's skin responds ``1 + change``
    times as strongly; fullness follows depth with a little press noise and no response change."""
    depth, rho2, rng = _presses(reps=6)
    depth, rho2 = np.concatenate([depth, depth]), np.concatenate([rho2, rho2])
    session = np.repeat([0, 1], depth.size // 2)
    strength = 20.0 * depth ** 1.3 * np.where(session == 1, 1.0 + change, 1.0)
    fullness = 10.0 + 4.0 * (depth + 0.03 * rng.standard_normal(depth.size))
    return {"strength": strength, "fullness": fullness}, depth, rho2, session


@pytest.mark.parametrize(("change", "chosen"), [(0.002, "strength"), (0.15, "fullness")])
def test_presses_of_two_sessions_measure_the_response_change_instead_of_the_prior(change, chosen):
    """Issue 37: each fold holds out a whole session, so the skin's real change between the days decides.
    A change far below the 5 % prior lets the exact (gain-sensitive) feature win; a large one loses it; with
    the same presses taken as one session, the prior alone decides (fullness both times)."""
    features, depth, rho2, session = _two_sessions(change)
    sel = select_feature(features, _presses_at(rho2, depth, session), 12.0)
    assert sel.by_session and sel.folds == 2 and sel.feature == chosen
    assert all(c.drift_rmse == 0.0 for c in sel.candidates)  # measured, not assumed
    # the held-out error of strength is the change the other day's fit could not know
    strength = {c.feature: c for c in sel.candidates}["strength"]
    assert strength.heldout_rmse == pytest.approx(np.sqrt(np.mean(depth ** 2)) * change / 1.3, rel=0.3)
    one = select_feature(features, _presses_at(rho2, depth), 12.0)
    assert not one.by_session and one.folds == 8 and one.feature == "fullness"


def test_sessions_fold_only_when_each_could_be_fitted_from_the_others():
    from optitac_edge.calibration.depth_fit import session_folds

    level = np.repeat([1.0, 2.0, 3.0], 4)
    assert session_folds(None, level) == 0
    assert session_folds(np.zeros(12, dtype=int), level) == 0  # one session: the prior
    assert session_folds(np.tile([0, 1, 2], 4), level) == 3
    assert session_folds(np.arange(12) % 10, level) == 0  # sessions with fewer than 3 depths each
    two_depths = np.array([0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1])  # session 1 only at 2.0 and 3.0
    assert session_folds(two_depths, np.array([1, 1, 2, 2, 3, 3, 2, 2, 3, 3, 3, 2], dtype=float)) == 0
