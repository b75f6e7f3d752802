"""Width calibration: a per-axis linear model, true diameter ≈ scale · (measured − offset)."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class WidthModel:
    """Linear width calibration of the major and minor axes (mm in, mm out)."""

    major_offset_mm: float
    major_scale: float
    minor_offset_mm: float
    minor_scale: float

    def correct(self, major_mm: float, minor_mm: float) -> tuple[float, float]:
        """Calibrated widths, clipped at 0."""
        return (max(self.major_scale * (major_mm - self.major_offset_mm), 0.0),
                max(self.minor_scale * (minor_mm - self.minor_offset_mm), 0.0))

    def to_bundle(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_bundle(cls, meta: dict[str, Any]) -> WidthModel:
        return cls(**{k: float(meta[k]) for k in ("major_offset_mm", "major_scale",
                                                  "minor_offset_mm", "minor_scale")})


def fit_axis(measured_mm: np.ndarray, true_mm: np.ndarray) -> tuple[float, float]:
    """Least-squares ``true = scale · (measured − offset)``; returns ``(offset, scale)``."""
    measured = np.asarray(measured_mm, dtype=np.float64)
    true = np.asarray(true_mm, dtype=np.float64)
    ok = np.isfinite(measured) & np.isfinite(true)
    if ok.sum() < 2 or np.ptp(measured[ok]) <= 0:
        raise ValueError("need presses of at least two different measured widths")
    scale, intercept = np.polyfit(measured[ok], true[ok], 1)
    return float(-intercept / scale), float(scale)


def fit_width_model(measured_major: np.ndarray, measured_minor: np.ndarray,
                    true_diameter: np.ndarray) -> WidthModel:
    """Fit both axes from circular presses of known diameter (arrays of shape (K,), mm)."""
    mo, ms = fit_axis(measured_major, true_diameter)
    no, ns = fit_axis(measured_minor, true_diameter)
    return WidthModel(mo, ms, no, ns)
