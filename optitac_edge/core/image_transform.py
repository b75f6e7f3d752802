"""The transform between the sensor's layout (mm) and the camera image (pixels).

Model, layout -> image (see docs/formats.md, "Orientation"):

1. mirror: ``x -> -x`` when ``mirror`` is set;
2. rotate counter-clockwise by ``rotation_deg`` (in the layout frame, +y up);
3. scale by ``scale_px_per_mm`` and place: ``u = cx + s*x``, ``v = cy - s*y``
   (u = column, v = row, image rows grow downwards);
4. radial lens distortion about (cx, cy): a point at distance r from the
   centre moves to ``r * (1 + k1 * (r / r_ref)**2)`` where ``r_ref`` is the
   layout radius in pixels (so ``k1`` is the relative stretch at the rim).

With rotation 0 and no mirror the layout's +x points to increasing column and
+y to decreasing row.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class ImageTransform:
    """Layout (mm) <-> image (px) transform; all angles in degrees."""

    rotation_deg: float
    scale_px_per_mm: float
    cx: float
    cy: float
    mirror: bool = False
    k1: float = 0.0
    r_ref_mm: float = 1.0

    def __post_init__(self) -> None:
        for name in ("rotation_deg", "scale_px_per_mm", "cx", "cy", "k1", "r_ref_mm"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"transform {name} must be a finite number, got {value!r}")
        if not self.scale_px_per_mm > 0 or not self.r_ref_mm > 0:
            raise ValueError("transform scale_px_per_mm and r_ref_mm must be > 0")
        if not isinstance(self.mirror, bool):
            raise TypeError(f"transform mirror must be true or false, got {self.mirror!r}")

    def to_dict(self) -> dict[str, float | bool]:
        return asdict(self)

    def _rotation(self) -> tuple[float, float]:
        t = math.radians(self.rotation_deg)
        return math.cos(t), math.sin(t)

    def layout_to_image(self, xy_mm: np.ndarray) -> np.ndarray:
        """Map layout points, shape (N, 2) mm, to image points, shape (N, 2) (col, row) px."""
        xy = np.asarray(xy_mm, dtype=np.float64)
        x = -xy[:, 0] if self.mirror else xy[:, 0]
        y = xy[:, 1]
        c, s = self._rotation()
        xr, yr = c * x - s * y, s * x + c * y
        du, dv = self.scale_px_per_mm * xr, -self.scale_px_per_mm * yr
        r_ref = self.scale_px_per_mm * self.r_ref_mm
        f = 1.0 + self.k1 * (du * du + dv * dv) / (r_ref * r_ref)
        return np.stack([self.cx + du * f, self.cy + dv * f], axis=1)
