"""Measure one contact's blob of the truncated surface: centroid, FWHM widths, angle, strength, shape.

The moments weigh the cells above ``max(truncation, peak_fraction * peak)``
(OpenCV's moments on the box, in mesh cells, then mm); the shape features
(log-Hu invariants and q4) binarise the blob at ``max(truncation,
shape_fraction * peak)``, or at the weighting level when ``shape_fraction``
is 0, with :class:`~optitac_edge.core.moments.BinaryShapeMoments`.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.grid import SurfaceGrid
from optitac_edge.core.levels import ContactLevels
from optitac_edge.core.moments import BinaryShapeMoments, ellipse_from_central, log_hu_value


class BlobMeasurer:
    """Measures blobs of an (n, n) mesh into :class:`ContactEstimate` objects; preallocated buffers.

    Parameters
    ----------
    grid : SurfaceGrid
        The mesh (cells -> mm).
    levels : ContactLevels
        The truncation level is read from here at every frame.
    min_area_mm2 : float
        Smallest contact area.
    peak_fraction, shape_fraction : float
        The weighting and binarisation levels as fractions of the blob's peak (0: off).
    """

    def __init__(self, grid: SurfaceGrid, levels: ContactLevels, min_area_mm2: float, peak_fraction: float,
                 shape_fraction: float) -> None:
        self.levels = levels
        self._min_area = float(min_area_mm2)
        self._cell_area = float(grid.cell_area_mm2)
        self._frac = float(peak_fraction)
        self._shape_frac = float(shape_fraction)
        # moments in mesh cells -> mm: x = x0 + step * col; second moments * step^2 * cell area
        self._x0, self._y0, self._step = float(grid.x0_mm), float(grid.y0_mm), float(grid.step_mm)
        self._mu2_scale = self._step * self._step * self._cell_area
        self._weighted = np.zeros(grid.n * grid.n, dtype=np.float32)
        self._shape_moments = BinaryShapeMoments(grid.n)

    def levels_of(self, peak: float) -> tuple[float, float]:
        """(weighting level, shape binarisation level) of a blob whose largest value is ``peak``."""
        trunc = float(self.levels.trunc)
        t = trunc
        if self._frac > 0.0 and self._frac * peak > t:
            t = float(np.float32(self._frac * peak))
        shape = max(trunc, self._shape_frac * peak) if self._shape_frac > 0.0 else t
        return t, shape

    def measure(self, img: np.ndarray, peak: float, cells: int, level: float | np.float32, out: ContactEstimate,
                x0: int, y0: int) -> bool:
        """Measure one blob into ``out``; whether it is a contact.

        ``img``: the blob's truncated surface (0 elsewhere), a box whose first
        cell is mesh column ``x0``, row ``y0``; ``peak``: its largest value;
        ``cells``: its cells above the truncation level; ``level``: the peak
        must exceed it (the on level, or the off level while in contact).
        """
        if not peak > level or cells * self._cell_area < self._min_area:
            return False
        t, shape_level = self.levels_of(peak)
        weighted = img
        if t > self.levels.trunc:
            h, w = img.shape
            weighted = self._weighted[:h * w].reshape(h, w)
            cv2.threshold(img, t, 0.0, cv2.THRESH_TOZERO, dst=weighted)
            cells = cv2.countNonZero(weighted)
        if not self.ellipse(weighted, x0, y0, out):
            return False
        out.area_mm2 = cells * self._cell_area
        out.peak = float(peak)
        self.shape_features(img, shape_level, out)
        out.shape = ""
        out.confidence = math.nan
        return True

    def ellipse(self, weighted: np.ndarray, x0: int, y0: int, out: ContactEstimate) -> bool:
        """Centroid, FWHM widths, angle and strength of a (box of the) truncated surface into ``out``;
        False when it holds nothing."""
        m = cv2.moments(weighted)
        m00 = m["m00"]
        if not m00 > 0.0:
            return False
        step, area = self._step, self._cell_area
        e = ellipse_from_central(
            m00 * area, self._x0 + step * (x0 + m["m10"] / m00), self._y0 + step * (y0 + m["m01"] / m00),
            m["mu20"] * self._mu2_scale, m["mu11"] * self._mu2_scale, m["mu02"] * self._mu2_scale)
        out.contact = True
        out.strength = e.strength
        out.x_mm, out.y_mm = e.x_mm, e.y_mm
        out.major_mm, out.minor_mm, out.angle_deg = e.major_mm, e.minor_mm, e.angle_deg
        return True

    def shape_features(self, img: np.ndarray, level: float, out: ContactEstimate) -> None:
        """Log-Hu invariants and q4 of ``img > level`` into ``out.hu`` / ``out.features`` (NaN if empty)."""
        hu, feats = out.hu, out.features
        got = self._shape_moments.hu_q4(img, level)
        if got is None:
            hu.fill(np.nan)
            feats.fill(np.nan)
            return
        h, feats[7] = got
        for i in range(7):
            hu[i] = feats[i] = log_hu_value(h[i])
