"""Fit the depth and force model (:class:`~optitac_edge.core.depth_model.DepthForceModel`) from presses
of known depth, and force when the rig carries a load cell.

Each target is ``h(feature * (1 + radial * rho^2))`` (see
:mod:`optitac_edge.core.depth_model`). The rig presses at a few commanded
depths (the levels); for every ``radial`` on a grid, ``h``'s knots are each
level's mean scaled feature and mean target, made monotone by an isotonic
regression (scikit-learn) weighted by the level's frames, and the ``radial``
with the smallest RMSE over the presses (each press one point, the mean of
its frames) wins. Knots at the levels, not at quantiles of the data: the
curve passes through what every level measured on average, whatever the
number of presses at each.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from optitac_edge.core.depth_model import RadialMonotoneMap
from optitac_edge.core.width_model import AxisMap

#: The radial gains tried.
RADIAL_GRID = tuple(float(v) for v in np.round(np.linspace(-0.8, 2.0, 57), 3))


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
    """Knots at each level's weighted mean (scaled feature, target), the targets made non-decreasing."""
    from sklearn.isotonic import IsotonicRegression

    means, w = grouped_means(np.stack([scaled, target], axis=1), level, weight)
    order = np.argsort(means[:, 0], kind="stable")
    x, y, w = means[order, 0], means[order, 1], w[order]
    keep = np.concatenate([[True], np.diff(x) > 0])  # equal features: one knot
    if keep.sum() < 2:
        return None
    y = IsotonicRegression(increasing=True).fit(x, y, sample_weight=w).predict(x)
    return AxisMap(x[keep], np.maximum.accumulate(y[keep]))


def fit_radial_monotone(feature: np.ndarray, rho2: np.ndarray, target: np.ndarray, radius_mm: float,
                        level: np.ndarray, weight: np.ndarray | None = None) -> RadialFit:
    """Fit ``target ~ h(feature * (1 + radial * rho2))`` over presses.

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
    for radial in RADIAL_GRID:
        scaled = f * (1.0 + radial * r2)
        curve = _curve(scaled, y, w, lv)
        if curve is None:
            continue
        pred = np.array([curve(v) for v in scaled])
        rmse = float(np.sqrt(np.average((pred - y) ** 2, weights=w)))
        if best is None or rmse < best.rmse - 1e-12:
            best = RadialFit(RadialMonotoneMap(radial, float(radius_mm), curve), rmse)
    if best is None or not np.ptp(best.model.curve.knots_true) > 0:
        raise ValueError("the target does not increase with the contact's feature")
    return best
