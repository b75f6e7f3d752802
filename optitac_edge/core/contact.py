"""The per-frame result of the pipeline."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Width of :attr:`ContactEstimate.features`: the 7 log-Hu invariants and q4.
N_FEATURES = 8


def _nan_hu() -> np.ndarray:
    return np.full(7, np.nan, dtype=np.float64)


def _nan_features() -> np.ndarray:
    return np.full(N_FEATURES, np.nan, dtype=np.float64)


@dataclass(slots=True)
class ContactEstimate:
    """Contact estimate of one frame.

    The runtime :class:`~optitac_edge.core.pipeline.Pipeline` reuses one instance
    for every frame (no allocation per frame); call :meth:`copy` to keep one.

    What belongs to the frame rather than to one contact (its index, time, whether the baseline is
    ready, how many contacts it has) is the frame's :class:`~optitac_edge.core.frame_result.FrameResult`'s.

    Attributes
    ----------
    contact : bool
        Area above the threshold >= ``ContactThresholds.min_area_mm2``.
    x_mm, y_mm : float
        Contact centroid in the sensor (layout) frame, mm. NaN without contact.
    major_mm, minor_mm : float
        FWHM widths along the major / minor axis of the second-moment ellipse,
        mm. NaN without contact.
    angle_deg : float
        Major-axis angle from +x towards +y, degrees, (-90, 90]. NaN without contact.
    strength : float
        ``m00`` of the truncated inverted surface, gray level * mm^2 (0 if
        nothing is above the threshold).
    area_mm2 : float
        Area of the surface above the threshold, mm^2.
    peak : float
        The largest value of the contact's inverted surface (the signal's units: gray levels, or a
        fraction of the rest level with the relative signal). NaN without contact.
    hu : ndarray, shape (7,), float64
        Log-scaled Hu invariants ``-sign(h) log10|h|`` of the binarised surface
        (shape features). NaN without contact.
    features : ndarray, shape (8,), float64
        The shape classifier's input: ``[hu[0] .. hu[6], q4]`` with ``q4 =
        |c40| / mu00**3`` (raw, not log) the rotation- and scale-invariant
        4-fold symmetry of the same binarised contact
        (:func:`~optitac_edge.core.moments.q4_from_central`: 0 for a disc, 1/60 for
        a square). NaN without contact.
    shape : str
        Classified contact shape; '' until a classifier exists.
    confidence : float
        Classifier confidence; NaN until a classifier exists.
    depth_mm : float
        Indentation depth, mm, from the bundle's depth model
        (:class:`~optitac_edge.core.depth_model.DepthForceModel`); NaN when not calibrated.
    force_n : float
        Normal force, N, from the same model when it was calibrated with a
        load cell; NaN otherwise.
    contact_id : int
        1 … 255, the same for one contact from the frame it touched in to its
        release (:class:`~optitac_edge.core.tracking.ContactTracker`); 0 without contact.
    touch_frame : int
        The frame (the result's ``frame``) this contact touched in; ``touch_frame == frame``
        in the frame of the touch. -1 without contact.
    vx_mm_s, vy_mm_s : float
        The contact's velocity in the sensor frame, mm/s: the least-squares slope of its last
        :data:`~optitac_edge.core.motion.WINDOW` centroids (fewer in its first frames;
        :class:`~optitac_edge.core.motion.ContactMotion`). NaN in the frame it touched in and without contact.
    sliding : bool
        The contact slides (gross motion above its own noise level) rather than being held.
    slide_frame : int
        The frame (the result's ``frame``) its current slide was found in; -1 while it is held and without contact.
    """

    contact: bool = False
    x_mm: float = math.nan
    y_mm: float = math.nan
    major_mm: float = math.nan
    minor_mm: float = math.nan
    angle_deg: float = math.nan
    strength: float = 0.0
    area_mm2: float = 0.0
    peak: float = math.nan
    hu: np.ndarray = field(default_factory=_nan_hu)
    features: np.ndarray = field(default_factory=_nan_features)
    shape: str = ""
    confidence: float = math.nan
    depth_mm: float = math.nan
    force_n: float = math.nan
    contact_id: int = 0
    touch_frame: int = -1
    vx_mm_s: float = math.nan
    vy_mm_s: float = math.nan
    sliding: bool = False
    slide_frame: int = -1

    def clear(self, strength: float = 0.0, area_mm2: float = 0.0) -> None:
        """No contact in this frame, in place: no id, no geometry; ``strength`` and ``area_mm2`` what was
        above the truncation level (0 when nothing was)."""
        self.contact = False
        self.strength = strength
        self.area_mm2 = area_mm2
        self.contact_id, self.touch_frame = 0, -1
        self.vx_mm_s = self.vy_mm_s = math.nan
        self.sliding, self.slide_frame = False, -1
        self.clear_geometry()

    def clear_geometry(self) -> None:
        """Set the geometric fields and shape features to NaN (no contact), in place."""
        self.x_mm = self.y_mm = math.nan
        self.major_mm = self.minor_mm = self.angle_deg = math.nan
        self.depth_mm = self.force_n = self.peak = math.nan
        self.hu.fill(np.nan)
        self.features.fill(np.nan)
        self.shape = ""
        self.confidence = math.nan

    def copy(self) -> ContactEstimate:
        """An independent copy (``hu`` and ``features`` copied)."""
        return ContactEstimate(
            contact=self.contact, x_mm=self.x_mm, y_mm=self.y_mm, major_mm=self.major_mm,
            minor_mm=self.minor_mm, angle_deg=self.angle_deg, strength=self.strength,
            area_mm2=self.area_mm2, peak=self.peak, hu=self.hu.copy(), features=self.features.copy(),
            shape=self.shape, confidence=self.confidence, depth_mm=self.depth_mm, force_n=self.force_n,
            contact_id=self.contact_id, touch_frame=self.touch_frame,
            vx_mm_s=self.vx_mm_s, vy_mm_s=self.vy_mm_s, sliding=self.sliding, slide_frame=self.slide_frame,
        )

    def assign(self, other: ContactEstimate) -> None:
        """Copy every field of ``other`` into this estimate, in place (arrays copied)."""
        self.contact, self.x_mm, self.y_mm = other.contact, other.x_mm, other.y_mm
        self.major_mm, self.minor_mm, self.angle_deg = other.major_mm, other.minor_mm, other.angle_deg
        self.strength, self.area_mm2, self.peak = other.strength, other.area_mm2, other.peak
        np.copyto(self.hu, other.hu)
        np.copyto(self.features, other.features)
        self.shape, self.confidence = other.shape, other.confidence
        self.depth_mm, self.force_n = other.depth_mm, other.force_n
        self.contact_id, self.touch_frame = other.contact_id, other.touch_frame
        self.vx_mm_s, self.vy_mm_s = other.vx_mm_s, other.vy_mm_s
        self.sliding, self.slide_frame = other.sliding, other.slide_frame

    def to_dict(self) -> dict[str, Any]:
        """JSON-able dict (NaN floats become None, ``hu`` and ``features`` lists)."""
        def f(v: float) -> float | None:
            return None if math.isnan(v) else float(v)

        return {
            "contact": bool(self.contact),
            "x_mm": f(self.x_mm), "y_mm": f(self.y_mm),
            "major_mm": f(self.major_mm), "minor_mm": f(self.minor_mm),
            "angle_deg": f(self.angle_deg), "strength": f(self.strength),
            "area_mm2": f(self.area_mm2), "peak": f(self.peak), "hu": [f(v) for v in self.hu],
            "features": [f(v) for v in self.features],
            "shape": self.shape, "confidence": f(self.confidence),
            "depth_mm": f(self.depth_mm), "force_n": f(self.force_n),
            "contact_id": int(self.contact_id),
            "touch_frame": int(self.touch_frame),
            "vx_mm_s": f(self.vx_mm_s), "vy_mm_s": f(self.vy_mm_s),
            "sliding": bool(self.sliding), "slide_frame": int(self.slide_frame),
        }
