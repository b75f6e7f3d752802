"""Steps 2-10 of a frame in numpy and OpenCV: the readable reference engine (:mod:`optitac_edge.core.pipeline`).

The steps are named parts, each with its own buffers and public methods (the benchmark times them one by
one): :class:`~optitac_edge.core.fiber_table.FiberSampler` (step 2),
:class:`~optitac_edge.core.gain.GainCompensation` (4), the surface operator (5),
:class:`~optitac_edge.core.segmentation.Segmenter` (6, 7: truncation and the split into contacts),
:class:`~optitac_edge.core.blob.BlobMeasurer` (7: the moments and shape features) and
:class:`~optitac_edge.core.baseline.BrightFibers` (10). The compiled engine
(:class:`~optitac_edge.core.compiled.CompiledEngine`) is built from these parts and shares their buffers.
"""

from __future__ import annotations

import numpy as np

from optitac_edge.core.baseline import Baseline, BrightFibers
from optitac_edge.core.blob import BlobMeasurer
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.contact_finder import ContactFinder
from optitac_edge.core.corrections import ContactCorrector
from optitac_edge.core.dead_fill import dead_fill_matrix
from optitac_edge.core.fiber_table import FiberSampler
from optitac_edge.core.frame_check import FrameCheck
from optitac_edge.core.frame_engine import MotionSteps, Skip, VibrationSteps
from optitac_edge.core.gain import GainCompensation, LedGain
from optitac_edge.core.levels import ContactLevels, banded
from optitac_edge.core.motion import ContactMotion
from optitac_edge.core.options import ContactOptions
from optitac_edge.core.segmentation import Segmenter
from optitac_edge.core.support import NeighbourSupport, neighbour_table
from optitac_edge.core.surface import DenseSurface, TriangleSurface
from optitac_edge.core.vibration import VibrationMeter


class NumpyEngine:
    """The numpy parts of one pipeline (a :class:`~optitac_edge.core.frame_engine.FrameEngine`).

    Parameters
    ----------
    bundle : CalibrationBundle
    options : ContactOptions
        The pipeline's contact options.
    baseline, levels : Baseline, ContactLevels
        The pipeline's (shared with the compiled engine).
    contacts : list of ContactEstimate
        The pipeline's contacts, ``MAX_CONTACTS`` of them; the frame's go to ``[:n]``.
    """

    def __init__(self, bundle: CalibrationBundle, options: ContactOptions, baseline: Baseline,
                 levels: ContactLevels, contacts: list[ContactEstimate]) -> None:
        o, table, grid = options, bundle.fibers, bundle.grid
        n_fibers = table.n_fibers
        self.bundle, self.options, self.baseline, self.levels, self.contacts = bundle, o, baseline, levels, contacts
        self.dead = np.flatnonzero(table.dead)
        #: Each fiber is live (not dead), shape (N,), bool.
        self.live = ~np.asarray(table.dead, dtype=bool)
        #: The live fibers' indices (every fiber's when none is live): what the LED gain is measured from.
        self.live_idx = np.flatnonzero(self.live) if self.live.any() else np.arange(n_fibers)
        #: The frame check (shape, dtype, dark, saturated).
        self.frame_check = FrameCheck(table, table.frame_shape)
        #: Step 2: the fiber means of a frame.
        self.sampler = FiberSampler(table, o.colour_mix)
        #: Step 10: a baseline taken over a press, found from fibers brighter than it.
        self.bright_fibers = BrightFibers(n_fibers, from_common=not o.compensate_gain)
        #: Step 4 with ``compensate_gain``: the frame's LED gain divided out (None when off).
        self.gain_compensation = (GainCompensation(self.live_idx, n_fibers, o.black_level, o.gain_rate_per_s,
                                                   o.relative)
                                  if o.compensate_gain else None)
        fill = dead_fill_matrix(bundle.layout.xy_mm, table.dead) if o.fill_dead and self.dead.size else None
        factors = bundle.surface_factors
        #: Step 5: the whole surface every frame, exactly: the factored Clough-Tocher form when the
        #: bundle has it (TriangleSurface: only the triangles near a contact), else the dense matrix.
        self.surface_op: TriangleSurface | DenseSurface = (
            TriangleSurface(factors, grid.n, fill=fill, fiber_xy=bundle.layout.xy_mm) if factors is not None
            else DenseSurface(np.asarray(bundle.interpolation), fill=fill))
        min_area = float(bundle.thresholds.min_area_mm2)
        #: Steps 6 and 7: truncation and the split into contacts.
        self.segmenter = Segmenter(grid.n, levels, min_area / float(grid.cell_area_mm2), o.split_fraction)
        #: Step 7: each contact's moments and shape features.
        self.blobs = BlobMeasurer(grid, levels, min_area, o.peak_fraction, o.shape_fraction)
        #: Steps 6 and 7 together: the frame's contacts into ``contacts``.
        self.finder = ContactFinder(self.segmenter, self.blobs, levels, contacts, o.max_contacts,
                                    float(grid.cell_area_mm2))
        #: Neighbour support of each fiber's signal (None: off).
        self.support = NeighbourSupport(neighbour_table(bundle.layout)) if o.support else None
        #: The shared buffers: the fiber means and the signal (N,), the truncated surface (n * n,), float32.
        self.means_buf = np.zeros(n_fibers, dtype=np.float32)
        self.signal_buf = np.zeros(n_fibers, dtype=np.float32)
        self.surface_buf = np.zeros(grid.n * grid.n, dtype=np.float32)
        self._clipped = np.zeros(n_fibers, dtype=np.float32)
        self._band_work = np.zeros(n_fibers, dtype=np.float32)
        self.corrector: ContactCorrector | None = None
        self.in_contact = False
        self.contact_end_ns: int | None = None
        self.saturated = self.light_changed = self.raise_pending = False
        self.rest = self.means_buf
        self.common = 0.0

    # -- the FrameEngine protocol ---------------------------------------------

    def check(self, frame: object) -> Skip | None:
        why = self.frame_check(frame)
        self.saturated = self.frame_check.saturated
        return None if why is None else Skip(why)

    def means(self, frame: np.ndarray) -> None:
        self.sampler.means(frame, self.means_buf)

    def run(self, frame: np.ndarray, now_ns: int, dt_ns: int) -> int:
        means = self.sampler.means(frame, self.means_buf)
        signal = self.compute_signal(means, now_ns)
        gain = self.gain_compensation
        self.light_changed = gain is not None and gain.light_changed
        surface = self.surface_op.compute(signal, self.surface_buf, self.levels.trunc)
        n = self.finder.find(surface, self.contacts[0], self.in_contact, self.corrector, self._gated(signal))
        self._follow_light(n, means, signal, now_ns, dt_ns)
        return n

    def set_levels(self, levels: ContactLevels) -> None:
        if self.gain_compensation is not None:
            self.gain_compensation.set_levels(levels.gain_delta, levels.gain_tolerance, levels.gain_significant)

    def reset_contact(self) -> None:
        self.in_contact = False
        self.contact_end_ns = None
        self.bright_fibers.reset()

    def reset_gain(self, now_ns: int | None) -> None:
        gain = self.gain_compensation
        if gain is not None:
            gain.reset_gain(gain.reference_ns if now_ns is None else now_ns)

    def led_gain(self) -> LedGain | None:
        return None if self.gain_compensation is None else self.gain_compensation.state()

    def use_corrector(self, corrector: ContactCorrector | None) -> None:
        self.corrector = corrector

    def motion_parts(self) -> tuple[MotionSteps, VibrationSteps]:
        return ContactMotion(), VibrationMeter(self.signal_buf, self.live)

    # -- the steps -------------------------------------------------------------

    def compute_signal(self, means: np.ndarray, now_ns: int) -> np.ndarray:
        """Step 4: the inverted signal of ``means`` (shape (N,)) into the signal buffer
        (:attr:`Pipeline.signal <optitac_edge.core.pipeline.Pipeline.signal>`)."""
        gain = self.gain_compensation
        if gain is not None:
            signal = gain.signal(means, self.baseline, now_ns, self.signal_buf)
        else:
            signal = np.subtract(self.baseline.values, means, out=self.signal_buf)
            if self.options.relative:
                np.multiply(signal, self.baseline.inv_level, out=signal)
        if self.dead.size:
            signal[self.dead] = 0.0
        if self.levels.bands is not None:  # each fiber's band (core/levels.py)
            banded(signal, self.levels.bands, self._clipped, self._band_work)
        return signal

    def _gated(self, signal: np.ndarray) -> bool:
        """With neighbour support: the frame's supported peak stays below the level (no contact)."""
        if self.support is None:
            return False
        level = self.levels.off if self.in_contact else self.levels.on
        return not self.support.peak(signal) > float(level)

    def _rest_light(self, means: np.ndarray) -> np.ndarray:
        """The frame's fiber means as the baseline takes them: with gain compensation, the LED gain divided
        out (per-fiber drift, not the LED's); a view valid until the next frame."""
        gain = self.gain_compensation
        return means if gain is None else gain.rest_means(self.baseline)

    def _follow_light(self, n: int, means: np.ndarray, signal: np.ndarray, now_ns: int, dt_ns: int) -> None:
        """Steps 9 and 10 after a frame with ``n`` contacts: fibers brighter than a baseline taken over a
        press to raise (:attr:`raise_pending`), else the baseline and the LED gain follow the light of
        contact-free frames."""
        baseline, gain = self.baseline, self.gain_compensation
        if n > 0:
            self.in_contact = True
        elif self.in_contact:
            self.in_contact = False
            self.contact_end_ns = now_ns
        off = float(self.levels.off)
        self.raise_pending = self.bright_fibers.check(signal, off, now_ns, n == 0)
        if self.raise_pending:
            self.rest, self.common = self._rest_light(means), self.bright_fibers.common
            return
        if n == 0 and gain is not None:
            gain.contact_free(now_ns)
        if n == 0 and self.options.track_baseline and dt_ns > 0:
            baseline.track(self._rest_light(means), signal, off, now_ns, dt_ns, self.contact_end_ns)
