"""The runtime pipeline: camera frame -> :class:`ContactEstimate`, per frame.

Per frame (the OptiTac method, see :mod:`optitac_edge.reference` for the
literal version):

1. check the frame against the bundle (shape, dtype, pixel format);
2. per-fiber mean gray level with the precomputed fiber table;
3. the first ``bundle.baseline_frames`` frames are averaged into the baseline
   (reported with ``baseline_ready=False``);
4. inverted signal ``baseline - mean`` (contacts darken fibers, so a contact is
   positive); dead fibers get 0 (a neighbour fill comes later);
5. surface = interpolation matrix @ signal (Clough-Tocher, 100 x 100 mesh);
6. truncate: values <= threshold become 0, values above are kept;
7. contact if the area above the threshold >= ``min_area_mm2``; then the
   moments give centroid, FWHM widths, angle and strength, and Hu invariants
   of the binarised surface give the shape features.

All buffers are allocated at construction; a frame costs no array allocation
beyond a few scalars. Only numpy is used.
"""

from __future__ import annotations

import math

import numpy as np

from .bundle import CalibrationBundle
from .contact import ContactEstimate
from .fiber_table import FiberSampler
from .moments import MomentBasis, ellipse_from_moments, hu_from_central, log_hu
from .surface import surface_from_fibers


class Pipeline:
    """Lean per-frame processing for one calibration bundle.

    Parameters
    ----------
    bundle : CalibrationBundle
        Frame size and pixel format, fiber table, interpolation matrix, grid,
        thresholds and number of baseline frames.

    Notes
    -----
    :meth:`process` returns the same :class:`ContactEstimate` object every
    call (updated in place); use ``estimate.copy()`` to keep one.
    """

    def __init__(self, bundle: CalibrationBundle) -> None:
        self.bundle = bundle
        table = bundle.fibers
        n_fibers = table.n_fibers
        grid = bundle.grid
        self._pixel_format = table.pixel_format
        self._sampler = FiberSampler(table)
        self._matrix = np.ascontiguousarray(bundle.interpolation, dtype=np.float32)
        self._dead = np.flatnonzero(table.dead)
        self._has_dead = self._dead.size > 0
        self._threshold = np.float32(bundle.thresholds.threshold)
        self._min_area = float(bundle.thresholds.min_area_mm2)
        self._cell_area = float(grid.cell_area_mm2)
        self._n_baseline = max(int(bundle.baseline_frames), 1)

        self._means = np.zeros(n_fibers, dtype=np.float32)
        self._baseline_sum = np.zeros(n_fibers, dtype=np.float64)
        self._baseline = np.zeros(n_fibers, dtype=np.float32)
        self._baseline_count = 0
        self._signal = np.zeros(n_fibers, dtype=np.float32)
        self._surface = np.zeros(grid.n * grid.n, dtype=np.float32)
        self._mask = np.zeros(grid.n * grid.n, dtype=bool)
        self._below = np.zeros(grid.n * grid.n, dtype=bool)
        self._basis = MomentBasis(grid, order=3)
        self._m = self._basis.new_moments()
        self._mu = self._basis.new_moments()
        self._mb = self._basis.new_moments()
        self._mub = self._basis.new_moments()
        self._hu = np.zeros(7, dtype=np.float64)
        self._frame = 0
        self._estimate = ContactEstimate()

    # -- state -----------------------------------------------------------------

    @property
    def baseline_ready(self) -> bool:
        return self._baseline_count >= self._n_baseline

    @property
    def baseline(self) -> np.ndarray:
        """Per-fiber baseline gray levels, shape (N,), float32 (zeros until ready)."""
        return self._baseline

    @property
    def surface(self) -> np.ndarray:
        """The last truncated inverted surface, shape (n, n), float32, gray levels.

        A view into the pipeline's buffer (overwritten by the next frame).
        """
        return self._surface.reshape(self.bundle.grid.n, self.bundle.grid.n)

    @property
    def signal(self) -> np.ndarray:
        """The last inverted per-fiber signal ``baseline - mean``, shape (N,), float32."""
        return self._signal

    def reset_baseline(self) -> None:
        """Tare: re-baseline from the next ``baseline_frames`` frames."""
        self._baseline_sum.fill(0.0)
        self._baseline_count = 0

    # -- per frame -------------------------------------------------------------

    def process(self, frame: np.ndarray, now_ns: int) -> ContactEstimate:
        """Contact estimate of one frame.

        Parameters
        ----------
        frame : ndarray, uint8
            A C-contiguous frame of the bundle's size and pixel format
            (gray (H, W), rgb (H, W, 3) or yuv420 (H*3//2, W)).
        now_ns : int
            Timestamp of the frame, ns (copied to ``t_ns``).

        Returns
        -------
        ContactEstimate
            The pipeline's reused estimate, updated in place.

        Raises
        ------
        FrameMismatchError
            If the frame's shape, dtype or format does not match the bundle.
        """
        table = self._sampler.table
        table.check_frame(frame, self._pixel_format)
        est = self._estimate
        est.frame = self._frame
        est.t_ns = now_ns
        self._frame += 1
        means = self._sampler.means(frame, self._means)

        if self._baseline_count < self._n_baseline:
            self._baseline_sum += means
            self._baseline_count += 1
            if self._baseline_count == self._n_baseline:
                np.multiply(self._baseline_sum, 1.0 / self._n_baseline, out=self._baseline,
                            casting="same_kind")
            est.baseline_ready = False
            est.contact = False
            est.strength = 0.0
            est.area_mm2 = 0.0
            est.clear_geometry()
            return est
        est.baseline_ready = True

        signal = np.subtract(self._baseline, means, out=self._signal)
        if self._has_dead:
            signal[self._dead] = 0.0
        surface = surface_from_fibers(self._matrix, signal, self._surface)
        np.greater(surface, self._threshold, out=self._mask)
        np.logical_not(self._mask, out=self._below)
        np.copyto(surface, 0.0, where=self._below)
        cells = int(np.count_nonzero(self._mask))
        area = cells * self._cell_area
        est.area_mm2 = area

        if cells == 0:
            est.strength = 0.0
            est.contact = False
            est.clear_geometry()
            return est
        m = self._basis.raw(surface, self._m)
        est.strength = float(m[0, 0])
        est.contact = bool(area >= self._min_area and m[0, 0] > 0.0)
        if not est.contact:
            est.clear_geometry()
            return est

        mu = self._basis.central(m, self._mu)
        e = ellipse_from_moments(m, mu)
        est.x_mm, est.y_mm = e.x_mm, e.y_mm
        est.major_mm, est.minor_mm, est.angle_deg = e.major_mm, e.minor_mm, e.angle_deg

        mb = self._basis.raw(self._mask, self._mb)
        mub = self._basis.central(mb, self._mub)
        hu_from_central(mub, out=self._hu)
        log_hu(self._hu, out=est.hu)
        est.shape = ""
        est.confidence = math.nan
        return est
