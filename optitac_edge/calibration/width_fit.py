"""Fit the width model from circular presses of known diameter: per axis, linear (the paper's)
or monotone piecewise-linear. The result, :class:`~optitac_edge.core.width_model.WidthModel`,
is applied per contact."""

from __future__ import annotations

import numpy as np

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
                    kind: str = "monotone") -> WidthModel:
    """Fit both axes from circular presses of known diameter (arrays of shape (K,), mm)."""
    if kind == "linear":
        return WidthModel("linear", AxisMap.linear(*fit_axis(measured_major, true_diameter)),
                          AxisMap.linear(*fit_axis(measured_minor, true_diameter)))
    if kind == "monotone":
        return WidthModel("monotone", fit_monotone_axis(measured_major, true_diameter),
                          fit_monotone_axis(measured_minor, true_diameter))
    raise ValueError(f"unknown width model kind {kind!r} (linear or monotone)")
