"""Fit the depth and force model (:class:`~optitac_edge.core.depth_model.DepthForceModel`) from presses
of known depth, and force when the rig carries a load cell; choose its input by held-out presses.

Each target is ``h(feature * (1 + radial * rho^(2 power)))`` (see
:mod:`optitac_edge.core.depth_model`). The rig presses at a few commanded
depths (the levels); for every ``radial`` on a grid (and ``power``, where the presses stand at enough
radii to tell it), ``h``'s knots are each
level's mean scaled feature and mean target, made monotone by an isotonic
regression (scikit-learn) weighted by the level's frames, and the ``radial``
with the smallest RMSE over the presses (each press one point, the mean of
its frames) wins. Knots at the levels, not at quantiles of the data: the
curve passes through what every level measured on average, whatever the
number of presses at each.

Which feature (:data:`~optitac_edge.core.depth_model.DEPTH_FEATURES`) a
real skin's depth follows is not known in advance, so every candidate is
fitted on some presses and judged on the others (:func:`select_feature`:
folds grouped by press, ``GroupKFold``; a press is never split). One
calibration session cannot show how the skin's response changes until the
next, so each candidate's held-out predictions are also taken with the
darkening-proportional features scaled by ``1 ± drift`` (:data:`RESPONSE_DRIFT`,
a prior stated in docs/calibration.md, not a figure of our simulator), and
the candidate with the smallest ``sqrt(held-out² + drift²)`` wins. Presses
from two sessions or more (days, each with its own baseline, each at 3 depths
or more) measure that change instead: every fold holds out a whole session,
so a candidate is judged on a day its fit never saw, and the prior drops
(:func:`session_folds`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from optitac_edge.calibration.folds import MAX_FOLDS, fold_count, held_out_errors
from optitac_edge.core.depth_model import GAIN_EXPONENT, RadialMonotoneMap
from optitac_edge.core.width_model import AxisMap

#: The radial gains tried.
RADIAL_GRID = tuple(float(v) for v in np.round(np.linspace(-0.8, 2.0, 57), 3))
#: The powers of ``rho^2`` tried, where the presses stand at :data:`POWER_RADII` distinct radii or more (two
#: radii, the centre and a ring, cannot tell a power from a gain: the quadratic stays).
RADIAL_POWERS = (1, 2, 4)
POWER_RADII = 3
#: How much the skin's response may change between days, relative (a gain on every fiber's darkening that
#: the rest frames cannot see, unlike the LED's): the prior the choice of feature guards against.
RESPONSE_DRIFT = 0.05
#: Presses the held-out choice needs at the least (each fold must keep 3 depths to fit).
MIN_SELECTION_PRESSES = 8


@dataclass(frozen=True)
class RadialFit:
    """One target's fit: the map and its RMSE over the calibration presses (target units)."""

    model: RadialMonotoneMap
    rmse: float


def grouped_means(values: np.ndarray, groups: np.ndarray, weights: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``values`` (shape (K,) or (K, M)) per group, weighted by ``weights`` (default: each row
    once), groups in sorted order; and each group's total weight (without weights: its row count)."""
    keys, inverse = np.unique(groups, return_inverse=True)
    inverse = inverse.ravel()
    v = np.asarray(values, dtype=np.float64)
    if weights is None:
        total = np.bincount(inverse, minlength=keys.size)
    else:
        total = np.bincount(inverse, weights=weights, minlength=keys.size)
        v = v * np.asarray(weights, dtype=np.float64).reshape(-1, *([1] * (v.ndim - 1)))
    sums = np.zeros((keys.size, *v.shape[1:]))
    np.add.at(sums, inverse, v)
    return sums / total.reshape(-1, *([1] * (v.ndim - 1))), total


def _curve(scaled: np.ndarray, target: np.ndarray, weight: np.ndarray, level: np.ndarray) -> AxisMap | None:
    """Knots at each level's weighted mean (scaled feature, target), the targets made non-decreasing (a
    weighted isotonic regression, equal features pooled first, as scikit-learn's IsotonicRegression does; scipy's
    function without its per-call validation: the fit runs ~10 000 times a calibration)."""
    from scipy.optimize import isotonic_regression

    means, w = grouped_means(np.stack([scaled, target], axis=1), level, weight)
    order = np.argsort(means[:, 0], kind="stable")
    x, y, w = means[order, 0], means[order, 1], w[order]
    # equal features (to rounding: means of equal values differ in their last bit) are one knot, their
    # weighted mean
    keep = np.concatenate([[True], np.diff(x) > 1e-12 * np.maximum(np.abs(x[1:]), 1.0)])
    if keep.sum() < 2:
        return None
    tie = np.cumsum(keep) - 1
    w_knot = np.bincount(tie, weights=w)
    y_knot = np.bincount(tie, weights=w * y) / w_knot
    fitted = isotonic_regression(y_knot, weights=w_knot, increasing=True).x
    return AxisMap(x[keep], np.maximum.accumulate(fitted))


def fit_radial_monotone(feature: np.ndarray, rho2: np.ndarray, target: np.ndarray, radius_mm: float,
                        level: np.ndarray, weight: np.ndarray | None = None) -> RadialFit:
    """Fit ``target ~ h(feature * (1 + radial * rho2 ** power))`` over presses (``power`` 1 unless the presses
    stand at :data:`POWER_RADII` radii or more).

    Parameters
    ----------
    feature, rho2, target : ndarray, shape (P,), float
        Per press: the contact's feature (width or strength), its squared radius over ``radius_mm``
        squared, and the true depth (mm) or force (N).
    radius_mm : float
        The array's radius, mm.
    level : ndarray, shape (P,)
        Per press: its commanded depth (the knots are the levels' means).
    weight : ndarray, shape (P,), optional
        Frames per press.

    Raises
    ------
    ValueError
        Fewer than 3 presses, or no increase of the target with the feature.
    """
    f, r2, y = (np.asarray(a, dtype=np.float64) for a in (feature, rho2, target))
    w = np.ones_like(f) if weight is None else np.asarray(weight, dtype=np.float64)
    ok = np.isfinite(f) & np.isfinite(r2) & np.isfinite(y) & (f > 0)
    f, r2, y, w, lv = f[ok], np.minimum(r2[ok], 1.0), y[ok], w[ok], np.asarray(level)[ok]
    if np.unique(lv).size < 3:
        raise ValueError(f"need presses at 3 depths or more, got {np.unique(lv).size}")
    best: RadialFit | None = None
    radii = np.unique(np.round(np.sqrt(r2), 1)).size  # tenths of the radius
    for power in RADIAL_POWERS if radii >= POWER_RADII else (1,):
        term = r2 ** power
        for radial in RADIAL_GRID:
            scaled = f * (1.0 + radial * term)
            curve = _curve(scaled, y, w, lv)
            if curve is None:
                continue
            pred = np.array([curve(v) for v in scaled])
            rmse = float(np.sqrt(np.average((pred - y) ** 2, weights=w)))
            if best is None or rmse < best.rmse - 1e-12:
                best = RadialFit(RadialMonotoneMap(radial, float(radius_mm), curve, power), rmse)
    if best is None or not np.ptp(best.model.curve.knots_true) > 0:
        raise ValueError("the target does not increase with the contact's feature")
    return best


@dataclass(frozen=True)
class Candidate:
    """One candidate input's error on presses held out of its fit (target units).

    Attributes
    ----------
    feature : str
    heldout_rmse : float
        RMSE of the held-out presses against their target, pooled over the folds (inf: could not be fitted).
    heldout_spread : float
        Standard deviation of the folds' RMSEs.
    drift_rmse : float
        RMS change of the held-out predictions when the skin's response is ``1 ± drift`` times as strong.
    """

    feature: str
    heldout_rmse: float
    heldout_spread: float
    drift_rmse: float

    @property
    def expected_rmse(self) -> float:
        """What to expect on presses of another day: ``sqrt(held-out² + drift²)``."""
        return float(np.hypot(self.heldout_rmse, self.drift_rmse))

    def to_dict(self) -> dict[str, float | str]:
        return {"feature": self.feature, "heldout_rmse": round(self.heldout_rmse, 4),
                "heldout_spread": round(self.heldout_spread, 4), "drift_rmse": round(self.drift_rmse, 4),
                "expected_rmse": round(self.expected_rmse, 4)}


@dataclass(frozen=True)
class Selection:
    """The chosen input, its fit on every press, and every candidate's held-out figures.

    ``by_session``: the folds held out whole sessions (the response change measured, no prior).
    """

    feature: str
    fit: RadialFit
    candidates: tuple[Candidate, ...]
    folds: int
    by_session: bool = False

    @property
    def chosen(self) -> Candidate:
        return next(c for c in self.candidates if c.feature == self.feature)


def predict(model: RadialMonotoneMap, feature: np.ndarray, rho2: np.ndarray) -> np.ndarray:
    """``model`` (the runtime's, per contact) over arrays of features and squared radii (over the array's)."""
    r = np.sqrt(np.minimum(rho2, 1.0)) * model.radius_mm
    return np.array([model(float(f), float(x), 0.0) for f, x in zip(feature, r)])


@dataclass(frozen=True, eq=False)
class Presses:
    """What a depth or force model is fitted to, per press: arrays of shape (P,) (see :func:`fit_radial_monotone`).

    ``rho2``: squared radius over the array's; ``target``: the depth (mm) or force (N); ``level``: the press's
    depth, for the monotone map's order; ``weight``: its frames; ``groups``: the press each row belongs to;
    ``session``: the session (recording) it was pressed in, when known.
    """

    rho2: np.ndarray
    target: np.ndarray
    level: np.ndarray
    weight: np.ndarray
    groups: np.ndarray
    session: np.ndarray | None = None


def held_out(feature: np.ndarray, p: Presses, radius_mm: float, exponent: float, drift: float = RESPONSE_DRIFT,
             folds: int = MAX_FOLDS, name: str = "") -> Candidate:
    """One candidate's held-out error: ``GroupKFold`` over ``p.groups`` (one group per press).

    Parameters
    ----------
    feature : ndarray, shape (P,)
        The candidate input, per press.
    p : Presses
    radius_mm : float
        The array's radius.
    exponent : float
        How the feature scales with the skin's response (``GAIN_EXPONENT``).
    drift : float
        The response change the drift term assumes.
    """
    rho2, target, level, weight = p.rho2, p.target, p.level, p.weight
    moved: list[np.ndarray] = []

    def error(train: np.ndarray, test: np.ndarray) -> np.ndarray:
        fit = fit_radial_monotone(feature[train], rho2[train], target[train], radius_mm, level[train],
                                  weight[train])
        pred = predict(fit.model, feature[test], rho2[test])
        for g in (1.0 + drift, 1.0 - drift):
            moved.append(predict(fit.model, feature[test] * g ** exponent, rho2[test]) - pred)
        return pred - target[test]

    try:
        out = held_out_errors(p.groups, folds, error)
    except ValueError:  # a fold that cannot be fitted
        return Candidate(name, float("inf"), float("inf"), float("inf"))
    if not np.isfinite(out.errors).all():
        return Candidate(name, float("inf"), float("inf"), float("inf"))
    m = np.concatenate(moved)
    return Candidate(name, float(out.rmse), out.spread, float(np.sqrt(np.mean(m ** 2))))


def session_folds(sessions: np.ndarray | None, level: np.ndarray) -> int:
    """How many folds of whole sessions the presses make: their number of sessions (at most ``MAX_FOLDS``)
    when there are two or more and each has presses at 3 levels or more (a fit on the others must stand at 3
    depths), else 0 (folds of presses, with the drift prior).

    Parameters
    ----------
    sessions : ndarray, shape (P,), or None
        The session (recording) of every press.
    level : ndarray, shape (P,)
        Every press's commanded depth.
    """
    if sessions is None:
        return 0
    keys = np.unique(sessions)
    if keys.size < 2 or any(np.unique(level[sessions == k]).size < 3 for k in keys):
        return 0
    return int(min(MAX_FOLDS, keys.size))


def select_feature(features: dict[str, np.ndarray], presses: Presses, radius_mm: float,
                   drift: float = RESPONSE_DRIFT) -> Selection:
    """Choose the input of ``target ~ h(feature * (1 + radial * rho2))`` by presses held out of the fit.

    Parameters
    ----------
    features : dict of str to ndarray, shape (P,)
        Per press: each candidate feature (names of ``GAIN_EXPONENT``), in the order ties are broken.
    presses : Presses
        The presses (as for :func:`held_out`); with two sessions or more (:func:`session_folds`) each fold
        holds out a session and ``drift`` is not used (the sessions measured the change).
    radius_mm : float
        The array's radius.
    drift : float
        The response change between days the choice guards against, when the presses come from one session.

    Raises
    ------
    ValueError
        Fewer than :data:`MIN_SELECTION_PRESSES` presses, or no candidate could be fitted.
    """
    folds = fold_count(presses.groups, MIN_SELECTION_PRESSES, "choose the model")
    by_session = session_folds(presses.session, np.asarray(presses.level))
    if by_session:
        assert presses.session is not None
        folds, drift = by_session, 0.0
        presses = replace(presses, groups=presses.session)
    candidates = []
    for name, value in features.items():
        v = np.asarray(value, dtype=np.float64)
        ok = np.isfinite(v) & (v > 0)
        if not ok.all():  # a candidate that is not defined for every press is not one
            continue
        candidates.append(held_out(v, presses, radius_mm, GAIN_EXPONENT[name], drift, folds, name))
    finite = [c for c in candidates if np.isfinite(c.expected_rmse)]
    if not finite:
        raise ValueError("no candidate model could be fitted on held-out presses")
    best = min(finite, key=lambda c: c.expected_rmse)  # first of equals: the simpler candidate
    fit = fit_radial_monotone(np.asarray(features[best.feature], dtype=np.float64), presses.rho2, presses.target,
                              radius_mm, presses.level, presses.weight)
    return Selection(best.feature, fit, tuple(candidates), folds, bool(by_session))
