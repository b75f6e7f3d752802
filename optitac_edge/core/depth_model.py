"""Indentation depth (mm) and normal force (N) of a contact, from its width (or strength) and position.

Fitted offline by :func:`optitac_edge.calibration.steps.calibrate_depth`
from presses of known depth (and force, when the rig carries a load cell).
The deeper an indenter goes, the wider the skin drapes around it: a
contact's width (the mean of its raw FWHM widths, mm) grows monotonically
with the depth, and, unlike its strength, does not change when the skin's
or the LED's response drifts from day to day (the FWHM is relative to the
contact's own peak). The clamped rim makes the skin respond less (and push
back harder) the further out the contact is, so each target is

``target = h(feature * (1 + radial * rho^(2 power)))``,  ``rho = r / radius_mm``

with ``h`` monotone increasing and piecewise linear (linear beyond its end
knots, clipped at 0), and ``radial`` and ``power`` (1, 2 or 4: on a wide
array the rim stiffens the skin only within a few pitches of it, a term
that stays flat over most of the radius) fitted per target. The feature is one
of :data:`DEPTH_FEATURES`, chosen per target at calibration by presses held
out of the fit (:mod:`optitac_edge.calibration.depth_fit`): how a real skin
darkens with depth is not known in advance. The model reads the raw
estimate (before the centroid map and the width model). It holds for the
indenter it was calibrated with (the ``depths`` experiment presses a 5 mm
circle): a wider indenter at the same depth reads deeper.

Per contact: a few float operations and a bisection (no numpy call).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from optitac_edge.core.width_model import AxisMap, rim_rho2

if TYPE_CHECKING:
    from optitac_edge.core.contact import ContactEstimate

#: The contact features a depth or force model may use, and how each scales when the skin's darkening is
#: multiplied by a gain ``g`` (the pins' response drifting between days): ``feature * g ** exponent``.
#:
#: ``width``            the mean of the raw FWHM widths, mm (relative to the contact's peak: 0)
#: ``strength``         the truncated surface's ``m00`` (1)
#: ``peak``             the contact's largest signal (1)
#: ``area``             the area above the weighting level, mm^2 (peak-relative by default: ~0)
#: ``fullness``         strength / peak, mm^2: the area of a flat top of the same volume (0)
#: ``strength_width``   strength * width (1)
#: ``root_strength_width``  sqrt(strength) * width (0.5)
#: ``fullness_width``   fullness * width, mm^3 (0)
GAIN_EXPONENT: dict[str, float] = {
    "width": 0.0, "strength": 1.0, "peak": 1.0, "area": 0.0, "fullness": 0.0,
    "strength_width": 1.0, "root_strength_width": 0.5, "fullness_width": 0.0,
}
DEPTH_FEATURES = tuple(GAIN_EXPONENT)
#: The largest power of ``rho^2`` a radial term may have (the kernel's limit too).
MAX_RADIAL_POWER = 4
#: The products with the width: feature -> (the other factor, its power).
_TIMES_WIDTH = {"strength_width": ("strength", 1.0), "root_strength_width": ("strength", 0.5),
                "fullness_width": ("fullness", 1.0)}


def depth_feature(est: Any, feature: str) -> Any:
    """The value of ``feature`` (one of :data:`DEPTH_FEATURES`) of a raw contact estimate (a float), or of
    per-frame arrays under the same names (the calibration's ``Measurements``: an array)."""
    if feature == "width":
        return 0.5 * (est.major_mm + est.minor_mm)
    if feature == "strength":
        return est.strength
    if feature == "peak":
        return est.peak
    if feature == "area":
        return est.area_mm2
    if feature == "fullness":
        return est.strength / est.peak
    if feature in _TIMES_WIDTH:
        other, power = _TIMES_WIDTH[feature]
        return depth_feature(est, other) ** power * depth_feature(est, "width")
    raise ValueError(f"unknown depth feature {feature!r} (known: {', '.join(DEPTH_FEATURES)})")


@dataclass(frozen=True, eq=False)
class RadialMonotoneMap:
    """``h(feature * (1 + radial * ((r / radius_mm)^2)^power))`` with ``h`` an :class:`AxisMap`.

    Attributes
    ----------
    radial : float
        The radial gain (> -1: the factor stays positive over the array).
    radius_mm : float
        The array's radius, mm (> 0).
    curve : AxisMap
        ``h``: scaled feature -> target.
    power : int
        The power of ``rho^2`` in the radial term, 1 to :data:`MAX_RADIAL_POWER` (1: the paper-sized
        array's quadratic).
    """

    radial: float
    radius_mm: float
    curve: AxisMap
    power: int = 1

    def __post_init__(self) -> None:
        if isinstance(self.power, bool) or not isinstance(self.power, int) or not 1 <= self.power <= MAX_RADIAL_POWER:
            raise ValueError(f"radial power must be an integer in 1..{MAX_RADIAL_POWER}, got {self.power!r}")
        if not (math.isfinite(self.radial) and self.radial > -1.0):
            raise ValueError(f"radial gain must be finite and > -1, got {self.radial!r}")
        if not (math.isfinite(self.radius_mm) and self.radius_mm > 0):
            raise ValueError(f"radius must be finite and > 0 mm, got {self.radius_mm!r}")

    def scaled(self, feature: float, x_mm: float, y_mm: float) -> float:
        """The feature times the radial factor at ``(x_mm, y_mm)`` (the factor capped at the rim)."""
        rho2 = rim_rho2(x_mm, y_mm, self.radius_mm)
        term = rho2
        for _ in range(1, self.power):  # the kernel's product, the same rounding
            term *= rho2
        return feature * (1.0 + self.radial * term)

    def __call__(self, feature: float, x_mm: float, y_mm: float) -> float:
        """The target (>= 0) of a contact; NaN when the feature or position is NaN."""
        v = self.scaled(float(feature), float(x_mm), float(y_mm))
        return math.nan if math.isnan(v) else self.curve(v)

    def kernel_arrays(self, prefix: str, feature: str) -> dict[str, Any]:
        """What the compiled kernel reads (:mod:`optitac_edge.core.compiled`), under ``prefix``."""
        return {**self.curve.kernel_arrays(prefix), f"{prefix}_feature": DEPTH_FEATURES.index(feature),
                f"{prefix}_radial": float(self.radial), f"{prefix}_radius_mm": float(self.radius_mm),
                f"{prefix}_power": int(self.power)}

    def to_dict(self) -> dict[str, Any]:
        return {"radial": self.radial, "radius_mm": self.radius_mm, "power": self.power,
                "knots_feature": self.curve.knots_measured.tolist(), "knots_target": self.curve.knots_true.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RadialMonotoneMap:
        curve = AxisMap(np.asarray(d["knots_feature"], dtype=np.float64), np.asarray(d["knots_target"], dtype=np.float64))
        if np.any(np.diff(curve.knots_true) < 0):
            raise ValueError("depth / force knots must not decrease")
        # bundles from before the power: the quadratic; checked in __post_init__
        return cls(float(d["radial"]), float(d["radius_mm"]), curve, d.get("power", 1))


@dataclass(frozen=True, eq=False)
class DepthForceModel:
    """Depth, and force when calibrated, of a contact.

    Attributes
    ----------
    feature : str
        The depth model's input, one of :data:`DEPTH_FEATURES`.
    depth : RadialMonotoneMap
        -> indentation depth, mm.
    force : RadialMonotoneMap or None
        -> normal force, N (None: no load cell in the calibration).
    force_feature : str
        The force model's input (default: ``feature``).
    """

    feature: str
    depth: RadialMonotoneMap
    force: RadialMonotoneMap | None = None
    force_feature: str = ""

    def __post_init__(self) -> None:
        if not self.force_feature:
            object.__setattr__(self, "force_feature", self.feature)
        for f in (self.feature, self.force_feature):
            if f not in DEPTH_FEATURES:
                raise ValueError(f"unknown depth feature {f!r} (known: {', '.join(DEPTH_FEATURES)})")

    def apply(self, est: ContactEstimate) -> None:
        """Set ``est.depth_mm`` and ``est.force_n`` (NaN without a force model) of one raw contact estimate."""
        x, y = est.x_mm, est.y_mm
        est.depth_mm = self.depth(depth_feature(est, self.feature), x, y)
        est.force_n = math.nan if self.force is None else self.force(depth_feature(est, self.force_feature), x, y)

    def kernel_arrays(self) -> dict[str, Any]:
        """What the compiled kernel reads (:mod:`optitac_edge.core.compiled`): the depth map, and the force map."""
        force = {} if self.force is None else self.force.kernel_arrays("force", self.force_feature)
        return {**self.depth.kernel_arrays("depth", self.feature), **force}

    def to_bundle(self) -> dict[str, Any]:
        return {"feature": self.feature, "depth": self.depth.to_dict(), "force_feature": self.force_feature,
                "force": None if self.force is None else self.force.to_dict()}

    @classmethod
    def from_bundle(cls, meta: dict[str, Any]) -> DepthForceModel:
        force = meta.get("force")
        return cls(str(meta["feature"]), RadialMonotoneMap.from_dict(meta["depth"]),
                   None if force is None else RadialMonotoneMap.from_dict(force),
                   str(meta.get("force_feature") or meta["feature"]))
