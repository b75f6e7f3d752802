"""Fit the centroid error maps (the paper's calibration) from presses of known position.

The error ``measured - true`` at each measured centroid fills two square
meshes by nearest neighbour through a k-d tree of the measured positions
(or linearly inside their hull); a Gaussian filter (the paper: sigma = 10
cells on a 1000-cell mesh) smooths the boundaries. The result,
:class:`~optitac_edge.core.centroid_map.CentroidErrorMap`, is looked up per contact.

:func:`held_out_fills` judges each fill on presses held out of the fit (``GroupKFold`` over presses), and
the raw estimate beside them (``none``: a map of zeros); :func:`choose_fill` adopts a map only where
held-out presses show it helps by more than their scatter (a few presses of a sparse, noisy sensor can make
a map that misplaces the presses it did not see).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from optitac_edge.calibration.folds import fold_count, held_out_errors, press_folds
from optitac_edge.core.centroid_map import MAP_CELLS, MAP_SIGMA_CELLS, CentroidErrorMap


def fit_centroid_map(
    measured_xy_mm: np.ndarray,
    true_xy_mm: np.ndarray,
    half_span_mm: float,
    cells: int = MAP_CELLS,
    sigma_cells: float = MAP_SIGMA_CELLS,
    fill: str = "nearest",
) -> CentroidErrorMap:
    """Fit the error maps from presses of known position.

    Parameters
    ----------
    measured_xy_mm, true_xy_mm : ndarray, shape (K, 2), float
        Measured and true centroids of K presses (or contact frames), mm.
    half_span_mm : float
        The meshes span ``[-half_span, +half_span]`` on both axes; choose it
        larger than the array so that every contact falls inside.
    cells : int
        Mesh size (the paper: 1000).
    sigma_cells : float
        Gaussian filter σ in cells (the paper: 10).
    fill : {"nearest", "linear", "none"}
        ``nearest``: the paper's k-d tree nearest-neighbour fill. ``linear``:
        piecewise-linear interpolation on the Delaunay triangulation of the
        measured positions inside their hull, nearest neighbour outside —
        no steps between presses for the filter to smooth. ``none``: no
        correction (maps of zeros).
    """
    from scipy.ndimage import gaussian_filter
    from scipy.spatial import cKDTree

    measured = np.asarray(measured_xy_mm, dtype=np.float64)
    error = measured - np.asarray(true_xy_mm, dtype=np.float64)
    ok = np.all(np.isfinite(measured), axis=1) & np.all(np.isfinite(error), axis=1)
    if ok.sum() < 3:
        raise ValueError(f"need at least 3 presses with a measured contact, got {int(ok.sum())}")
    measured, error = measured[ok], error[ok]
    axis = np.linspace(-half_span_mm, half_span_mm, cells)
    if fill == "none":
        zero = np.zeros((cells, cells), dtype=np.float32)
        return CentroidErrorMap(x0_mm=float(axis[0]), y0_mm=float(axis[0]), step_mm=float(axis[1] - axis[0]),
                                error_x=zero, error_y=zero.copy())
    xx, yy = np.meshgrid(axis, axis)
    points = np.stack([xx.ravel(), yy.ravel()], axis=1)
    _, nearest = cKDTree(measured).query(points)
    filled = error[nearest]
    if fill == "linear":
        from scipy.interpolate import LinearNDInterpolator

        linear = LinearNDInterpolator(measured, error)(points)
        inside = np.all(np.isfinite(linear), axis=1)
        filled[inside] = linear[inside]
    elif fill != "nearest":
        raise ValueError(f"unknown fill {fill!r}")
    maps = [gaussian_filter(filled[:, k].reshape(cells, cells), sigma_cells, mode="nearest") for k in (0, 1)]
    return CentroidErrorMap(
        x0_mm=float(axis[0]), y0_mm=float(axis[0]), step_mm=float(axis[1] - axis[0]),
        error_x=maps[0].astype(np.float32), error_y=maps[1].astype(np.float32),
    )


#: The fills ``calibrate centroid`` chooses among (``none``: the raw estimate, no map).
FILLS = ("nearest", "linear", "none")
#: The held-out check builds its maps on a mesh this many times coarser, the filter's sigma in mm unchanged.
HELD_OUT_COARSENING = 4


def held_out_fills(measured_xy_mm: np.ndarray, true_xy_mm: np.ndarray, groups: np.ndarray, half_span_mm: float,
                   fills: tuple[str, ...] = FILLS) -> list[dict[str, Any]]:
    """Each fill's error on presses held out of the map (``GroupKFold`` over ``groups``, one per press).

    Returns, per fill: the held-out RMSE per axis (mm, pooled over the folds), the spread (standard
    deviation) of the folds' RMSEs and their mean (the score). The maps of the check are
    :data:`HELD_OUT_COARSENING` times coarser than the runtime's (the same smoothing in mm).
    """
    return [summary for summary, _ in _fill_checks(measured_xy_mm, true_xy_mm, groups, half_span_mm, fills)]


def choose_fill(measured_xy_mm: np.ndarray, true_xy_mm: np.ndarray, groups: np.ndarray, half_span_mm: float,
                fills: tuple[str, ...] = FILLS) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The fill ``calibrate centroid`` adopts, and every fill's held-out figures (:func:`held_out_fills`).

    The fill with the smallest score, but the raw estimate (``none``, when among ``fills``) unless that fill
    places the held-out presses better by more than one standard error of the per-press difference of
    their squared errors: the one-standard-error rule (of models the held-out errors cannot tell apart,
    the simplest; Hastie, Tibshirani and Friedman, *The Elements of Statistical Learning*, 2nd ed., 7.10).
    The best map's candidate says by how much (``gain_mm2``, ``gain_se_mm2``: mean and standard error of
    the per-press difference, mm²).
    """
    checks = _fill_checks(measured_xy_mm, true_xy_mm, groups, half_span_mm, fills)
    best = min(range(len(checks)), key=lambda k: checks[k][0]["score_mm"])
    raw = next((k for k, (c, _) in enumerate(checks) if c["fill"] == "none"), None)
    if raw is not None and best != raw:
        gain = checks[raw][1] - checks[best][1]
        se = float(np.std(gain, ddof=1) / np.sqrt(gain.size)) if gain.size > 1 else math.inf
        checks[best][0].update(gain_mm2=round(float(gain.mean()), 4), gain_se_mm2=round(se, 4))
        if not float(gain.mean()) > se:
            best = raw
    return checks[best][0], [c for c, _ in checks]


def _fill_checks(measured_xy_mm: np.ndarray, true_xy_mm: np.ndarray, groups: np.ndarray, half_span_mm: float,
                 fills: tuple[str, ...]) -> list[tuple[dict[str, Any], np.ndarray]]:
    """Each fill's held-out figures and each press's mean squared held-out error (shape (presses,), mm²)."""
    measured, true = np.asarray(measured_xy_mm, dtype=np.float64), np.asarray(true_xy_mm, dtype=np.float64)
    folds = fold_count(groups, 4, "check the centroid map")
    cells = MAP_CELLS // HELD_OUT_COARSENING
    sigma = MAP_SIGMA_CELLS / HELD_OUT_COARSENING
    order = np.concatenate([test for _, test in press_folds(groups, folds)])  # the rows' order in the errors
    press = np.unique(np.asarray(groups), return_inverse=True)[1].ravel()
    frames_of = np.bincount(press).astype(np.float64)
    out = []
    for fill in fills:
        def error(train: np.ndarray, test: np.ndarray, fill: str = fill) -> np.ndarray:
            if fill == "none":
                return measured[test] - true[test]
            m = fit_centroid_map(measured[train], true[train], half_span_mm, cells, sigma, fill)
            return np.array([m.correct(x, y) for x, y in measured[test]]) - true[test]

        h = held_out_errors(groups, folds, error)
        squared = np.empty(order.size)
        squared[order] = np.sum(h.errors ** 2, axis=1)
        out.append(({"fill": fill, "heldout_rmse_mm": h.rmse.round(4).tolist(),
                     "heldout_spread_mm": round(h.spread, 4), "score_mm": round(float(h.rmse.mean()), 4)},
                    np.bincount(press, squared) / frames_of))
    return out
