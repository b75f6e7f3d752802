"""Centroid error maps (the paper's calibration), looked up per contact.

Fitted offline by :func:`optitac_edge.calibration.centroid_fit.fit_centroid_map`.
At run time the measured centroid is rounded to the nearest mesh cell and the
two map values there (x and y error) are subtracted: O(1).
"""

from __future__ import annotations

import math
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
        j = min(max(round(float((x_mm - self.x0_mm) / self.step_mm)), 0), n - 1)
        i = min(max(round(float((y_mm - self.y0_mm) / self.step_mm)), 0), n - 1)
        return x_mm - float(self.error_x[i, j]), y_mm - float(self.error_y[i, j])

    def kernel_arrays(self) -> dict[str, Any]:
        """What the compiled kernel reads (:mod:`optitac_edge.core.compiled`)."""
        return {"cmap_n": self.n, "cmap_x0": float(self.x0_mm), "cmap_y0": float(self.y0_mm),
                "cmap_step": float(self.step_mm), "cmap_ex": np.ascontiguousarray(self.error_x, dtype=np.float32),
                "cmap_ey": np.ascontiguousarray(self.error_y, dtype=np.float32)}

    def to_bundle(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        meta = {"x0_mm": self.x0_mm, "y0_mm": self.y0_mm, "step_mm": self.step_mm}
        return meta, {"centroid/error_x": self.error_x, "centroid/error_y": self.error_y}

    @classmethod
    def from_bundle(cls, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> CentroidErrorMap:
        ex = np.asarray(arrays["centroid/error_x"], dtype=np.float32)
        ey = np.asarray(arrays["centroid/error_y"], dtype=np.float32)
        if ex.ndim != 2 or ex.shape[0] != ex.shape[1] or ey.shape != ex.shape or ex.shape[0] < 2:
            raise ValueError("centroid error maps must be two square arrays of one size")
        if not (np.all(np.isfinite(ex)) and np.all(np.isfinite(ey))):
            raise ValueError("centroid error maps must be finite")
        x0, y0, step = float(meta["x0_mm"]), float(meta["y0_mm"]), float(meta["step_mm"])
        if not (math.isfinite(x0) and math.isfinite(y0) and math.isfinite(step) and step > 0):
            raise ValueError("centroid map origin must be finite and its step > 0")
        return cls(x0, y0, step, ex, ey)


