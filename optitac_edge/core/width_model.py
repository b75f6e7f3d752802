"""Width calibration per axis: measured FWHM width (mm) -> true contact width (mm).

``linear`` is the paper's model, ``true = scale · (measured − offset)``.
``monotone`` (beyond the paper) follows the measured response's curvature:
a monotone piecewise-linear map through the mean measured width of each
calibration diameter, extended linearly beyond the end knots. The skin's
response is not linear over 1.85–20 mm (small contacts saturate at the skin's
spread, large ones at the clamped rim), so a straight line leaves a
systematic error of about 0.3 mm that the monotone map removes.

Either may read the width scaled by ``1 + radial * rho^2`` (``rho = r /
radius_mm``, capped at the rim), one gain per axis: the clamped rim squeezes
a contact's darkening towards it, so the same circle reads narrower the
further out it is. ``calibrate width`` chooses the form by presses held out
of the fit (:mod:`optitac_edge.calibration.width_fit`).
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass, field
from typing import Any

import numpy as np

WIDTH_KINDS = ("linear", "monotone")


@dataclass(frozen=True, eq=False)
class AxisMap:
    """One axis: ``true = interp(measured, knots_measured, knots_true)``, linear beyond the ends.

    Attributes
    ----------
    knots_measured, knots_true : ndarray, shape (K,), float64, mm
        Increasing knots (K >= 2). A linear model has K = 2.
    """

    knots_measured: np.ndarray
    knots_true: np.ndarray
    # the knots as plain floats (set in __post_init__): per frame, bisect on a list
    _km: list[float] = field(init=False, repr=False)
    _kt: list[float] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        km, kt = self.knots_measured, self.knots_true
        if km.ndim != 1 or km.shape != kt.shape or km.size < 2 or np.any(np.diff(km) <= 0):
            raise ValueError("width knots must be two increasing arrays of one length >= 2")
        if not (np.all(np.isfinite(km)) and np.all(np.isfinite(kt))):
            raise ValueError("width knots must be finite")
        object.__setattr__(self, "_km", [float(v) for v in km])
        object.__setattr__(self, "_kt", [float(v) for v in kt])

    def __call__(self, measured: float) -> float:
        # per frame: plain floats and bisect (np.interp on one scalar costs microseconds)
        km, kt = self._km, self._kt
        measured = float(measured)
        if measured <= km[0]:
            k = 0
        elif measured >= km[-1]:
            k = len(km) - 2
        else:
            k = bisect_right(km, measured) - 1
            if measured == km[k]:
                return max(kt[k], 0.0)
        slope = (kt[k + 1] - kt[k]) / (km[k + 1] - km[k])
        return max(kt[k] + slope * (measured - km[k]), 0.0)

    def kernel_arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """The knots as the compiled kernel reads them, under ``prefix + "_km"`` and ``"_kt"``."""
        return {f"{prefix}_km": np.array(self._km, dtype=np.float64), f"{prefix}_kt": np.array(self._kt, dtype=np.float64)}

    @classmethod
    def linear(cls, offset_mm: float, scale: float) -> AxisMap:
        """The paper's ``true = scale · (measured − offset)`` as two knots."""
        return cls(np.array([offset_mm, offset_mm + 10.0]), np.array([0.0, 10.0 * scale]))


def rim_rho2(x_mm: float, y_mm: float, radius_mm: float) -> float:
    """``(r / radius_mm)^2`` of a contact at ``(x_mm, y_mm)``, capped at 1 (the rim); NaN for a NaN position.

    The radial factor ``1 + gain * rho^2`` of the width and depth models reads it (per contact: floats only).
    """
    return min((x_mm * x_mm + y_mm * y_mm) / (radius_mm * radius_mm), 1.0)


@dataclass(frozen=True, eq=False)
class WidthModel:
    """Width calibration of the major and minor axes.

    Attributes
    ----------
    kind : str
        One of :data:`WIDTH_KINDS`.
    major, minor : AxisMap
        Scaled measured width -> true width, per axis.
    radial_major, radial_minor : float
        Each axis' radial gain (> -1; 0, default: the width as measured).
    radius_mm : float
        The array's radius, mm (> 0).
    """

    kind: str
    major: AxisMap
    minor: AxisMap
    radial_major: float = 0.0
    radial_minor: float = 0.0
    radius_mm: float = 1.0

    def __post_init__(self) -> None:
        for v in (self.radial_major, self.radial_minor):
            if not (math.isfinite(v) and v > -1.0):
                raise ValueError(f"width radial gains must be finite and > -1, got {v!r}")
        if not (math.isfinite(self.radius_mm) and self.radius_mm > 0):
            raise ValueError(f"width model radius must be finite and > 0 mm, got {self.radius_mm!r}")

    def correct(self, major_mm: float, minor_mm: float, x_mm: float = 0.0, y_mm: float = 0.0
                ) -> tuple[float, float]:
        """Calibrated widths, mm, clipped at 0, of a contact at ``(x_mm, y_mm)`` (the raw centroid)."""
        if self.radial_major == 0.0 and self.radial_minor == 0.0:
            return self.major(major_mm), self.minor(minor_mm)
        rho2 = rim_rho2(x_mm, y_mm, self.radius_mm)
        if math.isnan(rho2):  # NaN position: as measured
            rho2 = 0.0
        return (self.major(major_mm * (1.0 + self.radial_major * rho2)),
                self.minor(minor_mm * (1.0 + self.radial_minor * rho2)))

    def kernel_arrays(self) -> dict[str, Any]:
        """What the compiled kernel reads (:mod:`optitac_edge.core.compiled`)."""
        return {**self.major.kernel_arrays("width_major"), **self.minor.kernel_arrays("width_minor"),
                "width_radial_major": float(self.radial_major), "width_radial_minor": float(self.radial_minor),
                "width_radius_mm": float(self.radius_mm)}

    def to_bundle(self) -> dict[str, Any]:
        return {"kind": self.kind, "radial_major": self.radial_major, "radial_minor": self.radial_minor,
                "radius_mm": self.radius_mm,
                **{f"{name}_{part}": getattr(getattr(self, name), f"knots_{part}").tolist()
                   for name in ("major", "minor") for part in ("measured", "true")}}

    @classmethod
    def from_bundle(cls, meta: dict[str, Any]) -> WidthModel:
        if meta.get("kind") not in WIDTH_KINDS:
            raise ValueError(f"unknown width model kind {meta.get('kind')!r}")
        axes = {name: AxisMap(np.asarray(meta[f"{name}_measured"], dtype=np.float64),
                              np.asarray(meta[f"{name}_true"], dtype=np.float64))
                for name in ("major", "minor")}
        return cls(kind=meta["kind"], **axes, radial_major=float(meta.get("radial_major", 0.0)),
                   radial_minor=float(meta.get("radial_minor", 0.0)), radius_mm=float(meta.get("radius_mm", 1.0)))


