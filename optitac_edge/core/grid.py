"""The surface grid: the square mesh the fiber values are interpolated onto.

``surface[i, j]`` is the value at ``(x_mm[j], y_mm[i])`` in the sensor frame;
``y_mm`` increases with the row index (so an image display of a surface is
upside down with respect to the camera image unless flipped).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from optitac_edge.core.layout import FiberLayout

DEFAULT_GRID_SIZE = 100
#: The mesh sizes a grid may have (a bundle claiming more is refused before anything is allocated).
MIN_GRID_SIZE, MAX_GRID_SIZE = 2, 4096


@dataclass(frozen=True)
class SurfaceGrid:
    """A square ``n`` x ``n`` mesh with spacing ``step_mm`` starting at ``(x0_mm, y0_mm)``."""

    n: int
    x0_mm: float
    y0_mm: float
    step_mm: float

    def __post_init__(self) -> None:
        if not isinstance(self.n, int) or isinstance(self.n, bool) or not MIN_GRID_SIZE <= self.n <= MAX_GRID_SIZE:
            raise ValueError(f"grid size n must be an integer in {MIN_GRID_SIZE}..{MAX_GRID_SIZE}, got {self.n!r}")
        for name in ("x0_mm", "y0_mm", "step_mm"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"grid {name} must be a finite number, got {value!r}")
        if not self.step_mm > 0:
            raise ValueError(f"grid step_mm must be > 0, got {self.step_mm!r}")

    @classmethod
    def over_layout(cls, layout: FiberLayout, n: int = DEFAULT_GRID_SIZE) -> SurfaceGrid:
        """The mesh spanning the layout's bounding box, square cells, centred on the box."""
        lo, hi = layout.xy_mm.min(axis=0), layout.xy_mm.max(axis=0)
        span = float((hi - lo).max())
        centre = (lo + hi) / 2.0
        return cls(n=n, x0_mm=float(centre[0] - span / 2), y0_mm=float(centre[1] - span / 2),
                   step_mm=span / (n - 1))

    @property
    def x_mm(self) -> np.ndarray:
        """Column coordinates, shape (n,), float64, mm."""
        return self.x0_mm + self.step_mm * np.arange(self.n)

    @property
    def y_mm(self) -> np.ndarray:
        """Row coordinates, shape (n,), float64, mm."""
        return self.y0_mm + self.step_mm * np.arange(self.n)

    @property
    def cell_area_mm2(self) -> float:
        return self.step_mm * self.step_mm

    def points(self) -> np.ndarray:
        """All mesh points in row-major order, shape (n*n, 2), float64, (x, y) mm."""
        xx, yy = np.meshgrid(self.x_mm, self.y_mm)
        return np.stack([xx.ravel(), yy.ravel()], axis=1)
