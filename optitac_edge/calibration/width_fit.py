"""Fit the width model from circular presses of known diameter: per axis, linear (the paper's)
or monotone piecewise-linear, each with or without a radial gain. The result,
:class:`~optitac_edge.core.width_model.WidthModel`, is applied per contact.

:func:`select_width_form` chooses among :data:`WIDTH_FORMS` by presses held out of the fit (``GroupKFold``
over presses: the frames of one press are never split between fit and check).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from optitac_edge.calibration.folds import fold_count, held_out_errors
from optitac_edge.core.width_model import AxisMap, WidthModel


def fit_axis(measured_mm: np.ndarray, true_mm: np.ndarray) -> tuple[float, float]:
    """Least-squares ``true = scale · (measured − offset)``; returns ``(offset, scale)``."""
    measured = np.asarray(measured_mm, dtype=np.float64)
    true = np.asarray(true_mm, dtype=np.float64)
    ok = np.isfinite(measured) & np.isfinite(true)
    if ok.sum() < 2 or np.ptp(measured[ok]) <= 0:
        raise ValueError("need presses of at least two different measured widths")
    scale, intercept = np.polyfit(measured[ok], true[ok], 1)
    return float(-intercept / scale), float(scale)


def fit_monotone_axis(measured_mm: np.ndarray, true_mm: np.ndarray) -> AxisMap:
    """Knots at each calibration diameter's mean measured width, made increasing.

    Means of diameters whose measured widths would not increase are pooled
    (pool-adjacent-violators), so the map is monotone.
    """
    measured = np.asarray(measured_mm, dtype=np.float64)
    true = np.asarray(true_mm, dtype=np.float64)
    ok = np.isfinite(measured) & np.isfinite(true)
    diameters = np.unique(true[ok])
    if diameters.size < 2:
        raise ValueError("need presses of at least two diameters")
    blocks = [[float(measured[ok][true[ok] == d].mean()), float(d), 1] for d in diameters]
    merged: list[list[float]] = []
    for m, t, w in blocks:  # pool adjacent violators on the measured means
        merged.append([m, t, w])
        while len(merged) > 1 and merged[-1][0] <= merged[-2][0]:
            m2, t2, w2 = merged.pop()
            m1, t1, w1 = merged.pop()
            merged.append([(m1 * w1 + m2 * w2) / (w1 + w2), (t1 * w1 + t2 * w2) / (w1 + w2), w1 + w2])
    if len(merged) < 2:
        raise ValueError("measured widths do not increase with the diameter")
    arr = np.array(merged)
    return AxisMap(arr[:, 0], arr[:, 1])


def fit_width_model(measured_major: np.ndarray, measured_minor: np.ndarray, true_diameter: np.ndarray,
                    kind: str = "monotone", radius_mm: float = 1.0) -> WidthModel:
    """Fit both axes from circular presses of known diameter (arrays of shape (K,), mm), without a radial gain
    (``radius_mm``: the array's, kept in the model)."""
    if kind not in ("linear", "monotone"):
        raise ValueError(f"unknown width model kind {kind!r} (linear or monotone)")
    return WidthModel(kind, _axis(kind, measured_major, true_diameter), _axis(kind, measured_minor, true_diameter),
                      radius_mm=radius_mm)


def _axis(kind: str, measured: np.ndarray, true: np.ndarray) -> AxisMap:
    return AxisMap.linear(*fit_axis(measured, true)) if kind == "linear" else fit_monotone_axis(measured, true)


#: The forms ``calibrate width`` chooses among.
WIDTH_FORMS = ("linear", "monotone", "linear-radial", "monotone-radial")
#: The radial gains a ``-radial`` form tries per axis.
RADIAL_GAINS = tuple(float(v) for v in np.round(np.arange(-0.3, 0.801, 0.02), 3))


def _radial_axis(kind: str, measured: np.ndarray, rho2: np.ndarray, true: np.ndarray) -> tuple[AxisMap, float]:
    """The axis map and radial gain with the smallest RMSE over the given frames."""
    best: tuple[float, AxisMap, float] | None = None
    for gain in RADIAL_GAINS:
        scaled = measured * (1.0 + gain * rho2)
        try:
            m = _axis(kind, scaled, true)
        except ValueError:
            continue
        rmse = float(np.sqrt(np.mean((np.array([m(v) for v in scaled]) - true) ** 2)))
        if best is None or rmse < best[0] - 1e-12:
            best = (rmse, m, gain)
    if best is None:
        raise ValueError("measured widths do not increase with the diameter")
    return best[1], best[2]


def fit_width_form(form: str, major: np.ndarray, minor: np.ndarray, rho2: np.ndarray, true: np.ndarray,
                   radius_mm: float) -> WidthModel:
    """Fit one of :data:`WIDTH_FORMS` (arrays of shape (K,): frames; ``rho2``: squared radius / radius_mm²)."""
    kind, _, radial = form.partition("-")
    if form not in WIDTH_FORMS:
        raise ValueError(f"unknown width model form {form!r} (known: {', '.join(WIDTH_FORMS)})")
    if not radial:
        return fit_width_model(major, minor, true, kind, radius_mm)
    r2 = np.minimum(rho2, 1.0)
    (major_map, g_major), (minor_map, g_minor) = (_radial_axis(kind, a, r2, true) for a in (major, minor))
    return WidthModel(kind, major_map, minor_map, g_major, g_minor, radius_mm)


def select_width_form(major: np.ndarray, minor: np.ndarray, rho2: np.ndarray, true: np.ndarray,
                      groups: np.ndarray, radius_mm: float, forms: tuple[str, ...] = WIDTH_FORMS
                      ) -> tuple[str, WidthModel, list[dict[str, Any]]]:
    """Choose the width model's form by presses held out of the fit.

    Parameters
    ----------
    major, minor, rho2, true : ndarray, shape (K,)
        Per frame: the raw widths (mm), the squared radius over ``radius_mm`` squared, the true diameter.
    groups : ndarray, shape (K,)
        The press of every frame.

    Returns
    -------
    form, model, candidates
        The chosen form, fitted on every frame; each form's held-out RMSE (major, minor; mm, pooled over
        the folds), the spread of the folds' RMSEs and their mean (the score).
    """
    folds = fold_count(groups, 4, "choose the width model")
    candidates: list[dict[str, Any]] = []
    for form in forms:
        def error(train: np.ndarray, test: np.ndarray, form: str = form) -> np.ndarray:
            m = fit_width_form(form, major[train], minor[train], rho2[train], true[train], radius_mm)
            pred = np.array([m.correct(a, b, math.sqrt(min(r, 1.0)) * radius_mm, 0.0)
                             for a, b, r in zip(major[test], minor[test], rho2[test])])
            return pred - true[test, None]

        try:
            out = held_out_errors(groups, folds, error)
        except ValueError:  # a fold that cannot be fitted
            continue
        candidates.append({"form": form, "heldout_rmse_mm": out.rmse.round(4).tolist(),
                           "heldout_spread_mm": round(out.spread, 4), "score_mm": round(float(out.rmse.mean()), 4)})
    if not candidates:
        raise ValueError("no width model could be fitted on held-out presses")
    best = min(candidates, key=lambda c: c["score_mm"])  # first of equals: the simpler form
    return best["form"], fit_width_form(best["form"], major, minor, rho2, true, radius_mm), candidates
