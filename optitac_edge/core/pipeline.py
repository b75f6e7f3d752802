"""The runtime pipeline: camera frame -> :class:`ContactEstimate`, per frame.

Per frame (the OptiTac method, see :mod:`optitac_edge.devtools.reference` for the
literal version, and :class:`~optitac_edge.core.bundle.ContactOptions` for the
switchable improvements beyond the paper noted in brackets):

1. check the frame against the bundle (shape, dtype, pixel format);
2. per-fiber mean gray level with the precomputed fiber table;
3. the first ``bundle.baseline_frames`` frames are averaged into the baseline
   (reported with ``baseline_ready=False``);
4. inverted signal ``baseline - mean`` (contacts darken fibers, so a contact is
   positive) [relative: divided by ``baseline - black_level``;
   compensate_gain: the fiber light above the black level first divided by
   the frame's common-mode LED gain, measured from the brightest-relative
   fibers and held near the last contact-free frame's gain during a contact];
   dead fibers get 0 [fill_dead: the mean of their neighbours, folded into
   the matrix];
5. surface = interpolation matrix @ signal (Clough-Tocher, 100 x 100 mesh),
   the whole mesh every frame, exactly, in the factored form
   (:class:`~optitac_edge.core.surface.PatchSurface`: the values and estimated
   gradients at the fibers, then 9 of them per mesh cell, tile by tile);
6. truncate: values <= threshold become 0, values above are kept
   [noise_levels: the truncation level is k * measured noise];
7. contact if the area above the threshold >= ``min_area_mm2`` [and the peak
   above the on level, or the off level while in contact (hysteresis);
   max_contacts > 1: each 8-connected blob is a contact; peak_fraction: each
   contact truncated at ``max(level, fraction * its peak)``]; then the
   moments give centroid, FWHM widths, angle and strength, and Hu invariants
   and the 4-fold symmetry q4 of the binarised surface give the shape
   features (``estimate.features``); everything after the truncation reads
   only the bounding box of the cells above the level (OpenCV's moments,
   threshold and labelling on views of it; the shape features from two small
   matrix products, :class:`~optitac_edge.core.moments.BinaryShapeMoments`);
8. [track_baseline: without contact, on quiet frames, the baseline follows
   the fiber means with a time constant of seconds (LED warm-up, drift; with
   compensate_gain the gain-compensated means: per-fiber drift)].

All buffers are allocated at construction; a frame allocates nothing that
outlives it (net 0 bytes per frame after warm-up, measured by
``optitac-edge bench``), only small temporaries: scalars, OpenCV's moment
dictionaries, and the partition's labels and counts when several contacts
are allowed and a frame has more than one blob or seed.
numpy and OpenCV only; see docs/performance.md.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager

import cv2
import numpy as np

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.corrections import ContactCorrector
from optitac_edge.core.dead_fill import dead_fill_matrix
from optitac_edge.core.fiber_table import FiberSampler
from optitac_edge.core.moments import BinaryShapeMoments, ellipse_from_central, log_hu_value
from optitac_edge.core.options import MAX_CONTACTS, ContactOptions
from optitac_edge.core.surface import DenseSurface, PatchSurface

#: Most blobs measured per frame (the largest by area) before the strongest are kept.
MAX_CANDIDATES = 8
#: compensate_gain: the LED gain of a frame with contact may differ from the last contact-free
#: frame's by this many truncation levels (plus ``gain_rate_per_s`` times the time since).
GAIN_TOLERANCE = 0.1
#: _partition's label for "all cells above the truncation level" (one blob, one seed).
WHOLE_MASK = -1


@contextmanager
def single_threaded_opencv() -> Iterator[None]:
    """OpenCV on the calling thread only, for the duration (restored after).

    The per-frame calls (labelling, moments, thresholds on a bounding box of a
    100 x 100 mesh) are far too small for OpenCV's thread pool: handing them to
    it costs more (thread wake-ups, ~10 µs a frame here) than it saves, and the
    pool's threads compete with the camera and link threads for the cores.
    The service and ``optitac-edge bench`` run the loop inside this.
    """
    previous = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(previous)


class Pipeline:
    """Lean per-frame processing for one calibration bundle.

    Parameters
    ----------
    bundle : CalibrationBundle
        Frame size and pixel format, fiber table, interpolation matrix, grid,
        thresholds, contact options and number of baseline frames.
    options : ContactOptions, optional
        Overrides ``bundle.options`` (e.g. ``ContactOptions.paper()`` or a
        ``dataclasses.replace`` of the bundle's options with one switch flipped).

    Notes
    -----
    :meth:`process` returns the same :class:`ContactEstimate` object every
    call (updated in place; the primary, i.e. strongest, contact); use
    ``estimate.copy()`` to keep one. All contacts of the frame are
    ``pipeline.contacts[:estimate.n_contacts]`` (also reused).
    """

    def __init__(self, bundle: CalibrationBundle, options: ContactOptions | None = None) -> None:
        self.bundle = bundle
        self.options = o = bundle.options if options is None else options
        table = bundle.fibers
        n_fibers = table.n_fibers
        grid = bundle.grid
        n_cells = grid.n * grid.n
        self._pixel_format = table.pixel_format
        self._sampler = FiberSampler(table)
        self._dead = np.flatnonzero(table.dead)
        self._has_dead = self._dead.size > 0
        self._live = ~np.asarray(table.dead, dtype=bool)
        fill = dead_fill_matrix(bundle.layout.xy_mm, table.dead) if o.fill_dead and self._has_dead else None
        # the whole surface every frame, exactly: the factored Clough-Tocher form when the bundle
        # has it (PatchSurface, ~4x less memory traffic), else the dense matrix
        factors = bundle.surface_factors
        self._surface_op: PatchSurface | DenseSurface = (
            PatchSurface(factors, grid.n, fill=fill) if factors is not None
            else DenseSurface(np.asarray(bundle.interpolation), fill=fill))
        self._min_area = float(bundle.thresholds.min_area_mm2)
        self._cell_area = float(grid.cell_area_mm2)
        self._n_baseline = max(int(bundle.baseline_frames), 1)
        self._multi = o.max_contacts > 1
        self._max_contacts = o.max_contacts
        self._frac = float(o.peak_fraction)
        self._shape_frac = float(o.shape_fraction)
        self._split_frac = float(o.split_fraction)
        self._tau_ns = float(o.baseline_tau_s) * 1e9
        self._holdoff_ns = float(o.holdoff_s) * 1e9
        # levels (truncation, off, on) in signal units, set when the baseline is ready
        self._trunc = self._off = self._on = np.float32(bundle.thresholds.threshold)
        self._on_override: float | None = None
        self._rest_level = 0.0
        # common-mode LED gain (compensate_gain): the last contact-free frame's gain, when
        # it was measured, the frame's gain, its tolerance and the cluster width (relative)
        self._gain_on = bool(o.compensate_gain)
        self._gain_ref = 1.0
        self._gain_ref_ns = 0
        self._gain = 1.0
        self._frame_gain_value = 1.0
        self._gain_tol = 0.0
        self._gain_delta = 0.0
        self._gain_rate = float(o.gain_rate_per_s) * 1e-9  # per ns
        self._black = np.float32(o.black_level)
        self._live_idx = np.flatnonzero(self._live)
        if self._live_idx.size == 0:
            self._live_idx = np.arange(n_fibers)
        self._live_ratio = np.zeros(self._live_idx.size, dtype=np.float32)
        self._ratio = np.zeros(n_fibers, dtype=np.float32)
        self._level = np.ones(n_fibers, dtype=np.float32)

        self._means = np.zeros(n_fibers, dtype=np.float32)
        self._baseline_sum = np.zeros(n_fibers, dtype=np.float64)
        self._baseline = np.zeros(n_fibers, dtype=np.float32)
        self._baseline_count = 0
        self._inv_denom = np.ones(n_fibers, dtype=np.float32)
        self._signal = np.zeros(n_fibers, dtype=np.float32)
        self._work = np.zeros(n_fibers, dtype=np.float32)
        self._mid = n_fibers // 2
        self._surface = np.zeros(n_cells, dtype=np.float32)
        self._n = grid.n
        self._mask2d = np.zeros((grid.n, grid.n), dtype=bool)
        self._mask_u8 = self._mask2d.view(np.uint8)
        # bounding-box sized scratch (contiguous (h, w) views at the start, see _roi)
        self._weighted = np.zeros(n_cells, dtype=np.float32)
        self._blob_img = np.zeros(n_cells, dtype=np.float32)
        self._split_mask = np.zeros(n_cells, dtype=bool)
        self._blob = np.zeros(n_cells, dtype=bool)
        self._below = np.zeros(n_cells, dtype=bool)
        self._labels = np.zeros(n_cells, dtype=np.int32)
        self._seed_labels = np.zeros(n_cells, dtype=np.int32)
        self._nearest = np.zeros((grid.n, grid.n), dtype=np.int32)
        # moments in mesh cells -> mm: x = x0 + step * col; second moments * step^2 * cell area
        self._x0, self._y0, self._step = float(grid.x0_mm), float(grid.y0_mm), float(grid.step_mm)
        self._mu2_scale = self._step * self._step * self._cell_area
        self._shape_moments = BinaryShapeMoments(grid.n)
        self._frame = 0
        self._in_contact = False
        self._last_ns: int | None = None
        self._contact_end_ns: int | None = None
        #: All contacts of the last frame, valid ``[:n_contacts]``, strongest first.
        self.contacts: list[ContactEstimate] = [ContactEstimate() for _ in range(MAX_CONTACTS)]
        self._estimate = self.contacts[0]
        self._cands = [ContactEstimate() for _ in range(MAX_CANDIDATES)]
        self._order = np.zeros(MAX_CANDIDATES, dtype=np.float64)
        #: Per-contact corrections (centroid error map, width model, shape), or None.
        #: Anything with ``apply(estimate)`` that corrects the estimate in place.
        self._corrector: ContactCorrector | None = None
        self.set_corrector(ContactCorrector(bundle))

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
        """The last truncated inverted surface, shape (n, n), float32, signal units.

        Truncated at the truncation level (gray levels, or relative units with
        ``options.relative``). A view into the pipeline's buffer (overwritten by
        the next frame).
        """
        return self._surface.reshape(self.bundle.grid.n, self.bundle.grid.n)

    @property
    def signal(self) -> np.ndarray:
        """The last inverted per-fiber signal, shape (N,), float32.

        ``baseline - mean`` (gray levels), or divided by ``baseline - black_level``
        with ``options.relative``; with ``options.compensate_gain`` the mean's
        light above the black level is divided by :attr:`gain` first; 0 for
        dead fibers.
        """
        return self._signal

    @property
    def levels(self) -> tuple[float, float, float]:
        """(truncation, off, on) levels in signal units (valid once the baseline is ready)."""
        return float(self._trunc), float(self._off), float(self._on)

    @property
    def in_contact(self) -> bool:
        return self._in_contact

    def set_contact_level(self, on_relative: float | None) -> None:
        """Set the contact-on level, in relative units of the rest light (None: the calibrated one).

        The off and truncation levels are lowered to it if they were higher.
        Kept across a tare.
        """
        if on_relative is not None and not on_relative > 0:
            raise ValueError(f"contact level must be > 0, got {on_relative!r}")
        self._on_override = on_relative
        if self.baseline_ready:
            self._set_levels()

    def reset_baseline(self) -> None:
        """Tare: re-baseline from the next ``baseline_frames`` frames."""
        self._baseline_sum.fill(0.0)
        self._baseline_count = 0
        self._in_contact = False
        self._contact_end_ns = None
        self._gain_ref = self._gain = 1.0

    def _baseline_updated(self) -> None:
        """Relative-signal denominators after a baseline change (217 values)."""
        if self.options.relative or self._gain_on:
            np.subtract(self._baseline, self._black, out=self._level)
            np.maximum(self._level, 1.0, out=self._level)
            np.reciprocal(self._level, out=self._inv_denom)

    def _set_levels(self) -> None:
        """Truncation / off / on levels in signal units (when the baseline is first ready)."""
        o = self.options
        live = self._baseline[self._live] if self._live.any() else self._baseline
        rest = float(np.median(live)) - o.black_level if live.size else 1.0
        self._rest_level = rest = max(rest, 1.0)
        unit = 1.0 if o.relative else rest  # signal units per relative unit
        if o.noise_levels:
            sigma = o.noise_rel if o.relative else o.noise_gray
            trunc = max(o.k_trunc * sigma, o.floor_trunc * unit)
            off = max(o.k_off * sigma, o.floor_off * unit, trunc)
            on = max(o.k_on * sigma, o.floor_on * unit, off)
        else:
            thr = self.bundle.thresholds.threshold
            trunc = off = on = thr / rest if o.relative else thr
        if self._on_override is not None:  # the MCU's SET_THRESHOLD
            on = self._on_override * unit
            off, trunc = min(off, on), min(trunc, on)
        if not o.hysteresis:
            off = on
        self._trunc, self._off, self._on = np.float32(trunc), np.float32(off), np.float32(on)
        # gain compensation, relative units: a fiber darker than the brightest cluster by the
        # off level is pressed; the gain may differ from the last contact-free frame's by
        # GAIN_TOLERANCE truncation levels (plus the drift rate) without evidence
        self._gain_delta = float(off) / unit
        self._gain_tol = GAIN_TOLERANCE * float(trunc) / unit

    # -- per frame -------------------------------------------------------------

    def set_corrector(self, corrector: ContactCorrector | None) -> None:
        """Apply ``corrector`` (the bundle's calibration models) to every contact; None: raw estimates.

        By default the bundle's own models are applied (numpy shape evaluator).
        """
        self._corrector = corrector if corrector is not None and corrector.active else None

    @property
    def calibrated(self) -> bool:
        """True when centroid and width calibrations are applied to the estimates."""
        return self._corrector is not None and self._corrector.calibrated

    def process(self, frame: np.ndarray, now_ns: int) -> ContactEstimate:
        """Contact estimate of one frame.

        Parameters
        ----------
        frame : ndarray, uint8
            A C-contiguous frame of the bundle's size and pixel format
            (gray (H, W), rgb (H, W, 3) or yuv420 (H*3//2, W)).
        now_ns : int
            Timestamp of the frame, ns (copied to ``t_ns``; the baseline
            tracking's clock).

        Returns
        -------
        ContactEstimate
            The pipeline's reused estimate of the primary (strongest) contact,
            updated in place; ``n_contacts`` tells how many of
            :attr:`contacts` are valid.

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
        dt_ns = 0 if self._last_ns is None else now_ns - self._last_ns
        self._last_ns = now_ns
        means = self._sampler.means(frame, self._means)

        if self._baseline_count < self._n_baseline:
            self._baseline_sum += means
            self._baseline_count += 1
            if self._baseline_count == self._n_baseline:
                np.multiply(self._baseline_sum, 1.0 / self._n_baseline, out=self._baseline,
                            casting="same_kind")
                self._baseline_updated()
                self._set_levels()
                self._gain_ref, self._gain, self._gain_ref_ns = 1.0, 1.0, now_ns
            est.baseline_ready = False
            self._no_contact(est, 0.0, 0.0)
            return est
        est.baseline_ready = True

        if self._gain_on:
            signal = self._compensated_signal(means, now_ns)
        else:
            signal = np.subtract(self._baseline, means, out=self._signal)
            if self.options.relative:
                np.multiply(signal, self._inv_denom, out=signal)
        if self._has_dead:
            signal[self._dead] = 0.0
        surface = self._surface_op.compute(signal, self._surface)
        n = self._find_contacts(surface, est)

        if n > 0:
            self._in_contact = True
        elif self._in_contact:
            self._in_contact = False
            self._contact_end_ns = now_ns
        if n == 0 and self._gain_on:
            # a contact-free frame: its own gain estimate is the reference from now on
            self._gain_ref, self._gain_ref_ns = self._frame_gain_value, now_ns
        if n == 0 and self.options.track_baseline and dt_ns > 0:
            if self._gain_on:  # follow the per-fiber drift, not the LED gain
                means = np.multiply(self._ratio, self._level, out=self._ratio)
                means /= np.float32(self._gain)
                means += self._black
            self._track(means, signal, now_ns, dt_ns)
        return est

    @property
    def gain(self) -> float:
        """The LED gain relative to the baseline the last frame was compensated with (1 if off)."""
        return self._gain

    def _compensated_signal(self, means: np.ndarray, now_ns: int) -> np.ndarray:
        """The signal with the frame's common-mode LED gain divided out (``compensate_gain``).

        ``ratio = (mean - black) / (baseline - black)`` per fiber is ``g (1 - d)``
        with ``g`` the LED gain and ``d >= 0`` the darkening, so the brightest
        fibers measure ``g``: the median of the ratios within ``delta`` (the off
        level) of the cluster around the upper quartile, twice. Limited to the last
        contact-free frame's gain +- ``tol + rate * elapsed``.
        """
        ratio = np.subtract(means, self._black, out=self._ratio)
        ratio *= self._inv_denom
        live = self._live_ratio
        ratio.take(self._live_idx, out=live)
        live.sort()
        n = live.size
        g = float(live[(3 * (n - 1)) // 4])
        keep = 1.0 - self._gain_delta
        for _ in range(2):
            j = int(live.searchsorted(np.float32(g * keep)))
            g = 0.5 * (float(live[(j + n - 1) // 2]) + float(live[(j + n) // 2]))
        self._frame_gain_value = g
        band = self._gain_tol + self._gain_rate * float(now_ns - self._gain_ref_ns)
        g = min(max(g, self._gain_ref - band), self._gain_ref + band)
        self._gain = g = max(g, 1e-3)
        signal = self._signal
        if self.options.relative:  # 1 - ratio / g
            np.multiply(ratio, np.float32(-1.0 / g), out=signal)
            signal += 1.0
        else:  # (baseline - black) - (mean - black) / g, gray levels
            np.multiply(ratio, np.float32(-1.0 / g), out=signal)
            signal += 1.0
            signal *= self._level
        return signal

    def _no_contact(self, est: ContactEstimate, strength: float, area: float) -> None:
        est.contact = False
        est.strength = strength
        est.area_mm2 = area
        est.n_contacts = 0
        est.clear_geometry()

    def _find_contacts(self, surface: np.ndarray, est: ContactEstimate) -> int:
        """Truncate the surface, find and measure the contacts; returns their number."""
        cells = self._truncate(surface)
        if cells == 0:
            self._no_contact(est, 0.0, 0.0)
            return 0
        level = self._off if self._in_contact else self._on
        # everything below reads only the bounding box of the cells above the truncation level
        img, mask, x, y, peak = self._box(surface)
        n_cand = 0
        if not self._multi:
            n_cand = self._measure_blob(img, peak, cells, level, self._cands[0], x, y)
        else:
            for k, blob_cells in self._partition(img, peak, mask, cells):
                blob = self._blob_surface(img, mask, k)
                n_cand += self._measure_blob(blob, peak if blob is img else cv2.minMaxLoc(blob)[1],
                                             blob_cells, level, self._cands[n_cand], x, y)
                if n_cand == MAX_CANDIDATES:
                    break
        if n_cand == 0:
            strength = float(cv2.sumElems(img)[0]) * self._cell_area
            self._no_contact(est, strength, cells * self._cell_area)
            return 0
        ranked: np.ndarray | range = range(1)
        if n_cand > 1:
            order = self._order[:n_cand]
            for i in range(n_cand):
                order[i] = -self._cands[i].strength
            ranked = np.argsort(order, kind="stable")
        n = min(n_cand, self._max_contacts)
        frame, t_ns = est.frame, est.t_ns
        for i in range(n):
            c = self.contacts[i]
            c.assign(self._cands[int(ranked[i])])
            c.frame, c.t_ns, c.baseline_ready, c.n_contacts = frame, t_ns, True, n
            if self._corrector is not None:
                self._corrector.apply(c)
        return n

    def _truncate(self, surface: np.ndarray) -> int:
        """Values <= the truncation level become 0, in place; the mask of the others; their count."""
        img = surface.reshape(self._n, self._n)
        cv2.threshold(img, float(self._trunc), 0.0, cv2.THRESH_TOZERO, dst=img)
        cells = cv2.countNonZero(img)
        if cells:  # the levels are > 0, so "above the level" is "not truncated to 0"
            np.greater(img, 0.0, out=self._mask2d)
        return cells

    def _box(self, surface: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int, float]:
        """The truncated surface and the mask in the bounding box of the cells above the level.

        Returns views ``(img, mask)`` of the box, its first mesh column and row, and the
        largest value of ``img`` (after :meth:`_truncate`, with at least one cell above).
        """
        x, y, w, h = cv2.boundingRect(self._mask_u8)
        img = surface.reshape(self._n, self._n)[y:y + h, x:x + w]
        return img, self._mask2d[y:y + h, x:x + w], x, y, float(cv2.minMaxLoc(img)[1])

    def _blob_levels(self, peak: float) -> tuple[float, float]:
        """(weighting level, shape binarization level) of a blob whose largest value is ``peak``.

        The moments weigh the cells above ``max(truncation, peak_fraction * peak)``;
        the shape features binarize at ``max(truncation, shape_fraction * peak)``,
        or at the weighting level when ``shape_fraction`` is 0.
        """
        t = float(self._trunc)
        if self._frac > 0.0 and self._frac * peak > t:
            t = float(np.float32(self._frac * peak))
        shape = max(float(self._trunc), self._shape_frac * peak) if self._shape_frac > 0.0 else t
        return t, shape

    def _roi(self, buffer: np.ndarray, h: int, w: int) -> np.ndarray:
        """A contiguous (h, w) view at the start of a flat (n*n,) buffer."""
        return buffer[:h * w].reshape(h, w)

    def _partition(self, img: np.ndarray, peak: float, mask: np.ndarray,
                   cells: int) -> list[tuple[int, int]]:
        """Split the truncated surface into contacts; ``(label, cells)`` of each, largest first.

        ``img`` and ``mask`` are the bounding box of the cells above the
        truncation level, ``peak`` the largest value of ``img``. The skin's spread joins neighbouring presses at the
        (low) noise level, so contacts are seeded by the blobs above
        ``split_fraction`` of the strongest peak, plus any blob of the
        truncated surface that holds no such seed (a weaker, separate press);
        every cell above the truncation level then belongs to its nearest seed.
        """
        h, w = img.shape
        split = max(float(self._trunc), self._split_frac * peak)
        seeds = self._roi(self._split_mask, h, w)
        np.greater(img, np.float32(split), out=seeds)
        labels = self._roi(self._labels, h, w)
        n_parts = cv2.connectedComponents(mask.view(np.uint8), labels=labels, connectivity=8,
                                          ltype=cv2.CV_32S)[0]
        min_cells = self._min_area / self._cell_area
        if n_parts == 2:  # one blob: it holds the peak, so it is one contact if its seeds are one
            n_seeds = cv2.connectedComponents(seeds.view(np.uint8), labels=self._roi(self._seed_labels, h, w),
                                              connectivity=8, ltype=cv2.CV_32S)[0]
            if n_seeds == 2:
                return [(WHOLE_MASK, cells)] if cells >= min_cells - 1e-9 else []
        seeded = np.zeros(n_parts, dtype=bool)
        seeded[labels[seeds]] = True
        # seeds: the strong blobs, and the truncated blobs without one
        blob = self._roi(self._blob, h, w)
        np.logical_or(seeds, np.logical_and(mask, ~seeded[labels]), out=blob)
        below = self._roi(self._below, h, w)
        np.logical_not(blob, out=below)
        _, self._nearest = cv2.distanceTransformWithLabels(
            below.view(np.uint8), cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_CCOMP)
        counts = np.bincount(self._nearest[mask], minlength=1)
        order = np.argsort(counts)[::-1]
        return [(int(k), int(counts[k])) for k in order if k > 0 and counts[k] >= min_cells - 1e-9]

    def _blob_surface(self, img: np.ndarray, mask: np.ndarray, label: int) -> np.ndarray:
        """The truncated surface of contact ``label`` alone (see _partition), bounding-box sized."""
        if label == WHOLE_MASK:
            return img
        h, w = img.shape
        blob = self._roi(self._blob, h, w)
        np.equal(self._nearest, label, out=blob)
        np.logical_and(blob, mask, out=blob)
        out = self._roi(self._blob_img, h, w)
        np.multiply(img, blob, out=out)
        return out

    def _measure_blob(self, img: np.ndarray, peak: float, cells: int, level: np.float32,
                      out: ContactEstimate, x0: int, y0: int) -> int:
        """Measure one blob into ``out``; 1 if it is a contact, else 0.

        ``img``: the blob's truncated surface (0 elsewhere), a box whose first
        cell is mesh column ``x0``, row ``y0``; ``peak``: its largest value.
        """
        if not peak > level or cells * self._cell_area < self._min_area:
            return 0
        t, shape_level = self._blob_levels(peak)
        weighted = img
        if t > self._trunc:
            weighted = self._roi(self._weighted, *img.shape)
            cv2.threshold(img, t, 0.0, cv2.THRESH_TOZERO, dst=weighted)
            cells = cv2.countNonZero(weighted)
        if not self._ellipse(weighted, x0, y0, out):
            return 0
        out.area_mm2 = cells * self._cell_area
        self._shape_features(img, shape_level, out)
        out.shape = ""
        out.confidence = math.nan
        return 1

    def _ellipse(self, weighted: np.ndarray, x0: int, y0: int, out: ContactEstimate) -> bool:
        """Centroid, FWHM widths, angle and strength of a (box of the) truncated surface into ``out``."""
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

    def _shape_features(self, img: np.ndarray, level: float, out: ContactEstimate) -> None:
        """Log-Hu invariants and q4 of ``img > level`` into ``out.hu`` / ``out.features``."""
        hu, feats = out.hu, out.features
        got = self._shape_moments.hu_q4(img, level)
        if got is None:
            hu.fill(np.nan)
            feats.fill(np.nan)
            return
        h, feats[7] = got
        for i in range(7):
            hu[i] = feats[i] = log_hu_value(h[i])

    def _track(self, means: np.ndarray, signal: np.ndarray, now_ns: int, dt_ns: int) -> None:
        """Slow baseline tracking on quiet contact-free frames."""
        if self._contact_end_ns is not None and now_ns - self._contact_end_ns < self._holdoff_ns:
            return
        # quiet: no fiber departs from the common level by the off level or more (a uniform
        # brightness drift is what the tracking is for; a press is local)
        work = self._work
        np.copyto(work, signal)
        work.partition(self._mid)
        common = work[self._mid]
        np.subtract(signal, common, out=work)
        np.abs(work, out=work)
        if float(work.max()) >= self._off:
            return
        alpha = np.float32(1.0 - math.exp(-min(float(dt_ns), self._tau_ns) / self._tau_ns))
        diff = np.subtract(means, self._baseline, out=self._work)
        diff *= alpha
        self._baseline += diff
        self._baseline_updated()
