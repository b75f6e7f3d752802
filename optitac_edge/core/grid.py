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
#: Mesh cells per fiber pitch of a bundle's mesh (the paper's array: 100 cells over its 16 pitches).
CELLS_PER_PITCH = 99 / 16
#: Most cells a side of a calibrated mesh has: the per-frame buffers and the dense interpolation matrix
#: (cells x fibers) grow with the square (1027 fibers on 100 x 100: 41 MiB); a larger array gets fewer
#: cells per pitch.
MAX_CALIBRATED_SIDE = DEFAULT_GRID_SIZE
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

    @classmethod
    def for_layout(cls, layout: FiberLayout) -> SurfaceGrid:
        """The mesh a bundle of ``layout`` is calibrated with: :data:`CELLS_PER_PITCH` cells a pitch over the
        layout's bounding box (at most :data:`MAX_CALIBRATED_SIDE` a side), whatever the pitch and fiber count:
        100 x 100 for the paper's 217 fibers at 1.5 mm, 51 x 51 for 61 fibers in 4 rings, 100 x 100
        (2.75 cells a pitch) for 1027 fibers in 18 rings."""
        lo, hi = layout.xy_mm.min(axis=0), layout.xy_mm.max(axis=0)
        pitches = float((hi - lo).max()) / layout.pitch_mm
        n = min(round(pitches * CELLS_PER_PITCH) + 1, MAX_CALIBRATED_SIDE)
        return cls.over_layout(layout, max(n, MIN_GRID_SIZE))

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
