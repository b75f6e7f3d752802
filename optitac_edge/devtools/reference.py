"""The OptiTac method done literally, per frame: test oracle and benchmark baseline.

Deliberately independent of :mod:`optitac_edge.core.pipeline`, :mod:`optitac_edge.core.surface`
and :mod:`optitac_edge.core.moments` (no shared code beyond the bundle and frame
formats): whole-frame grayscale, labelled means with ``scipy.ndimage.mean``,
``scipy.interpolate.griddata(method="cubic")`` every frame, and moments as
explicit sums over the mesh. Slow by design; use :class:`Pipeline` at runtime.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.interpolate import griddata

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.frame_result import FrameResult
from optitac_edge.core.frames import to_gray


class ReferencePipeline:
    """Literal per-frame implementation of the paper's method.

    Parameters
    ----------
    bundle : CalibrationBundle
        Uses the fiber table (as a label image), layout, grid, thresholds and
        number of baseline frames; ignores the interpolation matrix.
    """

    def __init__(self, bundle: CalibrationBundle) -> None:
        self.bundle = bundle
        self.labels = bundle.fibers.label_image()
        self.index = np.arange(1, bundle.fibers.n_fibers + 1)
        grid = bundle.grid
        self.X, self.Y = np.meshgrid(grid.x_mm, grid.y_mm)  # (n, n) each, mm
        self.dA = grid.step_mm * grid.step_mm
        self.baseline_values: list[np.ndarray] = []
        self.baseline: np.ndarray | None = None
        self.surface: np.ndarray | None = None
        self.frame_count = 0

    def reset_baseline(self) -> None:
        """Re-baseline from the next ``baseline_frames`` frames."""
        self.baseline_values = []
        self.baseline = None

    def process(self, frame: np.ndarray, now_ns: int) -> FrameResult:
        """The result of one frame (a new object each call): one contact at most, the paper's.

        Parameters
        ----------
        frame : ndarray, uint8
            Frame in the bundle's size and pixel format.
        now_ns : int
            Timestamp, ns.

        Returns
        -------
        FrameResult
        """
        b = self.bundle
        b.fibers.check_frame(frame, b.fibers.pixel_format)
        est = ContactEstimate()
        result = FrameResult([est], [], frame=self.frame_count, t_ns=now_ns)
        self.frame_count += 1

        gray = to_gray(frame, b.fibers.pixel_format)
        values = np.asarray(ndimage.mean(gray, labels=self.labels, index=self.index), dtype=np.float64)

        if self.baseline is None:
            self.baseline_values.append(values)
            if len(self.baseline_values) >= max(b.baseline_frames, 1):
                self.baseline = np.mean(self.baseline_values, axis=0)
            return result
        result.baseline_ready = True

        delta = values - self.baseline
        delta[b.fibers.dead] = 0.0
        Z = griddata(b.layout.xy_mm, delta, (self.X, self.Y), method="cubic", fill_value=0.0)
        inv = -Z
        I = np.where(inv > b.thresholds.threshold, inv, 0.0)
        self.surface = I

        X, Y, dA = self.X, self.Y, self.dA
        area = np.sum(I > 0) * dA
        m00 = np.sum(I) * dA
        est.area_mm2 = float(area)
        est.strength = float(m00)
        est.contact = bool(np.sum(I > 0) > 0 and area >= b.thresholds.min_area_mm2 and m00 > 0)
        if not est.contact:
            return result
        result.n_contacts = 1

        m10 = np.sum(X * I) * dA
        m01 = np.sum(Y * I) * dA
        xbar, ybar = m10 / m00, m01 / m00
        mu20 = np.sum((X - xbar) ** 2 * I) * dA / m00
        mu02 = np.sum((Y - ybar) ** 2 * I) * dA / m00
        mu11 = np.sum((X - xbar) * (Y - ybar) * I) * dA / m00
        lam1 = (mu20 + mu02) / 2 + np.sqrt(4 * mu11**2 + (mu20 - mu02) ** 2) / 2
        lam2 = (mu20 + mu02) / 2 - np.sqrt(4 * mu11**2 + (mu20 - mu02) ** 2) / 2
        fwhm = 2 * np.sqrt(2 * np.log(2))
        theta = 0.5 * np.degrees(np.arctan2(2 * mu11, mu20 - mu02))
        if theta <= -90:
            theta += 180
        est.x_mm, est.y_mm = float(xbar), float(ybar)
        est.major_mm = float(fwhm * np.sqrt(max(lam1, 0.0)))
        est.minor_mm = float(fwhm * np.sqrt(max(lam2, 0.0)))
        est.angle_deg = float(theta)
        est.hu[:] = _log_hu(_hu_literal((I > 0).astype(np.float64), X, Y, dA))
        return result


def _hu_literal(B: np.ndarray, X: np.ndarray, Y: np.ndarray, dA: float) -> np.ndarray:
    """Hu's invariants of binary image ``B`` on mesh ``X, Y`` (mm), written out."""
    m00 = np.sum(B) * dA
    xbar = np.sum(X * B) * dA / m00
    ybar = np.sum(Y * B) * dA / m00

    def eta(p: int, q: int) -> float:
        mu = np.sum((X - xbar) ** p * (Y - ybar) ** q * B) * dA
        return mu / m00 ** (1 + (p + q) / 2)

    n20, n02, n11 = eta(2, 0), eta(0, 2), eta(1, 1)
    n30, n03, n21, n12 = eta(3, 0), eta(0, 3), eta(2, 1), eta(1, 2)
    h1 = n20 + n02
    h2 = (n20 - n02) ** 2 + 4 * n11**2
    h3 = (n30 - 3 * n12) ** 2 + (3 * n21 - n03) ** 2
    h4 = (n30 + n12) ** 2 + (n21 + n03) ** 2
    h5 = ((n30 - 3 * n12) * (n30 + n12) * ((n30 + n12) ** 2 - 3 * (n21 + n03) ** 2)
          + (3 * n21 - n03) * (n21 + n03) * (3 * (n30 + n12) ** 2 - (n21 + n03) ** 2))
    h6 = ((n20 - n02) * ((n30 + n12) ** 2 - (n21 + n03) ** 2)
          + 4 * n11 * (n30 + n12) * (n21 + n03))
    h7 = ((3 * n21 - n03) * (n30 + n12) * ((n30 + n12) ** 2 - 3 * (n21 + n03) ** 2)
          - (n30 - 3 * n12) * (n21 + n03) * (3 * (n30 + n12) ** 2 - (n21 + n03) ** 2))
    return np.array([h1, h2, h3, h4, h5, h6, h7], dtype=np.float64)


def _log_hu(h: np.ndarray) -> np.ndarray:
    out = np.zeros_like(h)
    nz = h != 0
    out[nz] = -np.sign(h[nz]) * np.log10(np.abs(h[nz]))
    return out


def reference_surface(bundle: CalibrationBundle, delta: np.ndarray) -> np.ndarray:
    """griddata-cubic surface of baseline-subtracted fiber values, shape (n, n), float64."""
    X, Y = np.meshgrid(bundle.grid.x_mm, bundle.grid.y_mm)
    return griddata(bundle.layout.xy_mm, delta, (X, Y), method="cubic", fill_value=0.0)


__all__ = ["ReferencePipeline", "reference_surface"]
