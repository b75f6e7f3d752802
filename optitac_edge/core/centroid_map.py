"""Centroid error maps (the paper's calibration): fitted offline, looked up per contact.

Fitting (offline, scipy): from presses of known position, the error
``measured − true`` at each measured centroid fills two square meshes (x and
y error) by nearest neighbour through a k-d tree of the measured positions;
a Gaussian filter (σ = 10 cells) smooths the boundaries. At run time the
measured centroid is rounded to the nearest mesh cell and the two map values
there are subtracted: O(1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

#: The paper's mesh size and filter width.
MAP_CELLS = 1000
MAP_SIGMA_CELLS = 10.0


@dataclass(frozen=True, eq=False)
class CentroidErrorMap:
    """Two error maps on one square mesh.

    Attributes
    ----------
    x0_mm, y0_mm : float
        Sensor-frame position of cell (0, 0), mm.
    step_mm : float
        Cell size, mm.
    error_x, error_y : ndarray, shape (n, n), float32
        Measured-minus-true centroid error, mm; ``error[i, j]`` at
        ``(x0 + j·step, y0 + i·step)``.
    """

    x0_mm: float
    y0_mm: float
    step_mm: float
    error_x: np.ndarray
    error_y: np.ndarray

    @property
    def n(self) -> int:
        return int(self.error_x.shape[0])

    def correct(self, x_mm: float, y_mm: float) -> tuple[float, float]:
        """The calibrated centroid: the measured one minus the map value at the nearest cell."""
        n = self.error_x.shape[0]
        j = min(max(int(round((x_mm - self.x0_mm) / self.step_mm)), 0), n - 1)
        i = min(max(int(round((y_mm - self.y0_mm) / self.step_mm)), 0), n - 1)
        return x_mm - float(self.error_x[i, j]), y_mm - float(self.error_y[i, j])

    def to_bundle(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        meta = {"x0_mm": self.x0_mm, "y0_mm": self.y0_mm, "step_mm": self.step_mm}
        return meta, {"centroid/error_x": self.error_x, "centroid/error_y": self.error_y}

    @classmethod
    def from_bundle(cls, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> CentroidErrorMap:
        ex = np.asarray(arrays["centroid/error_x"], dtype=np.float32)
        ey = np.asarray(arrays["centroid/error_y"], dtype=np.float32)
        if ex.ndim != 2 or ex.shape[0] != ex.shape[1] or ey.shape != ex.shape:
            raise ValueError("centroid error maps must be two square arrays of one size")
        return cls(float(meta["x0_mm"]), float(meta["y0_mm"]), float(meta["step_mm"]), ex, ey)


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
    fill : {"nearest", "linear"}
        ``nearest``: the paper's k-d tree nearest-neighbour fill. ``linear``:
        piecewise-linear interpolation on the Delaunay triangulation of the
        measured positions inside their hull, nearest neighbour outside —
        no steps between presses for the filter to smooth.
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
