"""The runtime pipeline: camera frame -> :class:`ContactEstimate`, per frame.

Per frame (the OptiTac method, see :mod:`optitac_edge.devtools.reference` for the
literal version, and :class:`~optitac_edge.core.bundle.ContactOptions` for the
switchable improvements beyond the paper noted in brackets):

1. (the caller's) the frame is checked against the bundle: shape, dtype, pixel
   format, dark or saturated (:class:`~optitac_edge.core.frame_check.FrameCheck`,
   once per frame; the pipeline takes a checked frame);
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
   in the factored form (:class:`~optitac_edge.core.surface.TriangleSurface`:
   the values and estimated gradients at the fibers, then 9 of them per mesh
   cell, only in the triangles that can exceed the truncation level: after
   step 6 exactly the whole mesh's surface);
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
8. the contacts get stable ids, the frame they touched in, and the contacts
   of the previous frame that are gone are released
   (:class:`~optitac_edge.core.tracking.ContactTracker`; ``result.released``);
   8b. each contact's velocity from its last few centroids and whether it
   slides (:class:`~optitac_edge.core.motion.ContactMotion`), and the fibers'
   signal energy above a cut-off frequency, the frame's vibration
   (:class:`~optitac_edge.core.vibration.VibrationMeter`; ``result.vibration``);
9. [track_baseline: without contact, on quiet frames, the baseline follows
   the fiber means with a time constant of seconds (LED warm-up, drift; with
   compensate_gain the gain-compensated means: per-fiber drift)];
10. fibers brighter than their baseline by the off level, which no press can
   make, for :data:`~optitac_edge.core.baseline.BRIGHT_HOLD_S` and a frame
   without contact: the baseline was taken while the skin was pressed there (a
   start or a tare during a grasp); those fibers' baseline is raised to their
   light (:class:`~optitac_edge.core.baseline.BrightFibers`;
   ``result.baseline_raised``, ``result.raised_fibers``).

Everything a frame gave is one :class:`~optitac_edge.core.frame_result.FrameResult`.

The steps are named parts, each with its own buffers and public methods (the
benchmark times them one by one): :class:`~optitac_edge.core.fiber_table.FiberSampler`
(step 2), :class:`~optitac_edge.core.baseline.Baseline` (3, 9),
:class:`~optitac_edge.core.gain.GainCompensation` (4),
:class:`~optitac_edge.core.levels.ContactLevels`, the surface operator (5),
:class:`~optitac_edge.core.segmentation.Segmenter` (6, 7: truncation and the
split into contacts), :class:`~optitac_edge.core.blob.BlobMeasurer` (7: the
moments and shape features), :class:`~optitac_edge.core.corrections.ContactCorrector`
(the calibration models) and :class:`~optitac_edge.core.tracking.ContactTracker` (8).

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

from optitac_edge.core.baseline import Baseline, BrightFibers
from optitac_edge.core.blob import BlobMeasurer
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.compiled import FrameKernel, compiled_motion, compiled_vibration, kernel_status
from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.contact_finder import ContactFinder
from optitac_edge.core.corrections import ContactCorrector
from optitac_edge.core.dead_fill import dead_fill_matrix
from optitac_edge.core.fiber_table import FiberSampler
from optitac_edge.core.frame_check import FrameCheck
from optitac_edge.core.frame_result import FrameResult
from optitac_edge.core.gain import GainCompensation, LedGain
from optitac_edge.core.levels import ContactLevels, FiberModel, banded
from optitac_edge.core.motion import ContactMotion
from optitac_edge.core.options import MAX_CONTACTS, ContactOptions
from optitac_edge.core.segmentation import Segmenter
from optitac_edge.core.support import NeighbourSupport, neighbour_table
from optitac_edge.core.surface import DenseSurface, TriangleSurface
from optitac_edge.core.tracking import GATE_PITCH, ContactTracker
from optitac_edge.core.vibration import VibrationMeter


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


def _track(pipe: Pipeline, n: int, now_ns: int, dt_ns: int | None) -> None:
    """Steps 8 and 8b: ids, touches and releases of the frame's ``n`` contacts (``result.contacts``) into the
    pipeline's result; then (``dt_ns`` given: the baseline is ready) their motion and the frame's vibration."""
    result, tracker = pipe.result, pipe.tracker
    tracker.update(result.contacts, n, result.frame, pipe.after_gap)
    result.n_contacts = n
    result.n_released = tracker.n_released
    if dt_ns is None:
        result.vibration, result.vibrating, result.vibration_began = math.nan, False, False
        return
    pipe.motion.update(result.contacts, n, result.frame, now_ns)
    meter = pipe.vibration
    result.vibration = meter.update(float(pipe.levels.trunc), dt_ns)
    result.vibrating, result.vibration_began = meter.vibrating, meter.began


def _motion_parts(signal: np.ndarray, live: np.ndarray, compiled: bool) -> tuple[ContactMotion, VibrationMeter]:
    """Step 8b's parts: the kernel's (``compiled``) or the numpy ones."""
    if compiled:
        return compiled_motion(), compiled_vibration(signal, live)
    return ContactMotion(), VibrationMeter(signal, live)


def _rest_light(means: np.ndarray, gain: GainCompensation | None, baseline: Baseline) -> np.ndarray:
    """The frame's fiber means (shape (N,), gray levels) as the baseline takes them: with gain compensation,
    the LED gain divided out (per-fiber drift, not the LED's); a view valid until the next frame."""
    return means if gain is None else gain.rest_means(baseline)


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
    compiled : bool, optional
        Run the frames in the compiled kernel (:mod:`optitac_edge.core.compiled`):
        None (default) when it is built, True requires it (ImportError if not
        built), False the numpy parts (the reference).
    fps : float, optional
        The camera's nominal frame rate, frames/s (:meth:`set_frame_rate`): the vibration filter is designed
        for it, and a contact's velocity window whose frames span less than half their nominal time gives no
        velocity. None: not known (the filter takes the first frame interval; no window is refused).

    Notes
    -----
    :meth:`process` returns the same :class:`FrameResult` object every call
    (updated in place): ``result.primary`` is the primary (strongest) contact's
    :class:`ContactEstimate`, ``result.contacts[:result.n_contacts]`` every
    contact; use ``result.primary.copy()`` to keep one.
    """

    def __init__(self, bundle: CalibrationBundle, options: ContactOptions | None = None,
                 compiled: bool | None = None, fps: float | None = None) -> None:
        self.bundle = bundle
        self.options = o = bundle.options if options is None else options
        table = bundle.fibers
        n_fibers = table.n_fibers
        grid = bundle.grid
        self._dead = np.flatnonzero(table.dead)
        self._has_dead = self._dead.size > 0
        self._live = ~np.asarray(table.dead, dtype=bool)
        live_idx = np.flatnonzero(self._live)
        #: Step 2: the fiber means of a frame.
        self.sampler = FiberSampler(table, o.colour_mix)
        #: Step 3 and 9: the rest light, averaged then tracked.
        self.baseline = Baseline(n_fibers, bundle.baseline_frames, o.black_level, o.baseline_tau_s, o.holdoff_s)
        #: Step 10: a baseline taken over a press, found from fibers brighter than it.
        self.bright_fibers = BrightFibers(n_fibers, from_common=not o.compensate_gain)
        #: The truncation, off and on levels.
        self.levels = ContactLevels(o, bundle.thresholds.threshold, FiberModel(bundle))
        #: Step 4 with ``compensate_gain``: the frame's LED gain divided out (None when off).
        self.gain_compensation = (GainCompensation(live_idx if live_idx.size else np.arange(n_fibers), n_fibers,
                                                   o.black_level, o.gain_rate_per_s, o.relative)
                                  if o.compensate_gain else None)
        fill = dead_fill_matrix(bundle.layout.xy_mm, table.dead) if o.fill_dead and self._has_dead else None
        factors = bundle.surface_factors
        #: Step 5: the whole surface every frame, exactly: the factored Clough-Tocher form when the
        #: bundle has it (TriangleSurface: only the triangles near a contact), else the dense matrix.
        self.surface_op: TriangleSurface | DenseSurface = (
            TriangleSurface(factors, grid.n, fill=fill, fiber_xy=bundle.layout.xy_mm) if factors is not None
            else DenseSurface(np.asarray(bundle.interpolation), fill=fill))
        min_area = float(bundle.thresholds.min_area_mm2)
        #: Steps 6 and 7: truncation and the split into contacts.
        self.segmenter = Segmenter(grid.n, self.levels, min_area / float(grid.cell_area_mm2), o.split_fraction)
        #: Step 7: each contact's moments and shape features.
        self.blobs = BlobMeasurer(grid, self.levels, min_area, o.peak_fraction, o.shape_fraction)
        self._means, self._signal = np.zeros(n_fibers, dtype=np.float32), np.zeros(n_fibers, dtype=np.float32)
        self._clipped = np.zeros(n_fibers, dtype=np.float32)
        self._band_work = np.zeros(n_fibers, dtype=np.float32)
        #: Neighbour support of each fiber's signal (None: off).
        self.support = NeighbourSupport(neighbour_table(bundle.layout)) if o.support else None
        self._surface = np.zeros(grid.n * grid.n, dtype=np.float32)
        self._n, self._frame, self._in_contact = grid.n, 0, False
        self._last_ns: int | None = None
        self._gap_ns = round(o.gap_s * 1e9)
        #: The last frame followed a gap longer than ``options.gap_s``: it was processed as a snapshot.
        self.after_gap = False
        self._contact_end_ns: int | None = None
        #: All contacts of the last frame, valid ``[:n_contacts]``, strongest first.
        self.contacts: list[ContactEstimate] = [ContactEstimate() for _ in range(MAX_CONTACTS)]
        self._estimate = self.contacts[0]
        #: Steps 6 and 7 together: the frame's contacts into :attr:`contacts`.
        self.finder = ContactFinder(self.segmenter, self.blobs, self.levels, self.contacts, o.max_contacts,
                                    float(grid.cell_area_mm2))
        #: Stable contact ids, touch frames and releases from frame to frame.
        self.tracker = ContactTracker(GATE_PITCH * bundle.layout.pitch_mm, max_contacts=MAX_CONTACTS)
        #: What the last frame gave (the object :meth:`process` returns, updated in place).
        self.result = FrameResult(self.contacts, self.tracker.released)
        #: The compiled kernel running steps 2-10 (None: the numpy parts do).
        self.kernel: FrameKernel | None = None
        #: Per-contact corrections (centroid error map, width model, shape), or None.
        self.corrector: ContactCorrector | None = None
        self.set_corrector(ContactCorrector(bundle))
        if compiled or (compiled is None and kernel_status()[0]):
            self.kernel = FrameKernel(self)  # it keeps the contacts' shape features where it writes them
            self.set_corrector(self.corrector)
        #: Step 8b: every contact's velocity and slip state, and the fibers' vibration.
        self.motion, self.vibration = _motion_parts(self._signal, self._live, self.kernel is not None)
        if fps is not None:
            self.set_frame_rate(fps)

    def set_frame_rate(self, fps: float) -> None:
        """The camera's nominal frame rate, frames/s (the motion's and vibration's period; see the class).

        Raises
        ------
        ValueError
            Unless ``fps`` is a finite number > 0.
        """
        if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"a frame rate must be a finite number > 0, got {fps!r}")
        self.motion.period_s = self.vibration.period_s = 1.0 / float(fps)

    # -- state -----------------------------------------------------------------

    @property
    def baseline_ready(self) -> bool:
        return self.baseline.ready

    @property
    def means(self) -> np.ndarray:
        """The last frame's fiber means, shape (N,), float32 (gray levels)."""
        return self._means

    @property
    def surface(self) -> np.ndarray:
        """The last truncated inverted surface, shape (n, n), float32, signal units.

        Truncated at the truncation level (gray levels, or relative units with
        ``options.relative``). A view into the pipeline's buffer (overwritten by
        the next frame).
        """
        return self._surface.reshape(self._n, self._n)

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
    def led_gain(self) -> LedGain | None:
        """The LED gain compensation's state after the last frame (``.gain``: the gain relative to the
        baseline the frame was compensated with); None without ``compensate_gain``."""
        if self.gain_compensation is None:
            return None
        return self.gain_compensation.state() if self.kernel is None else self.kernel.led_gain()

    def set_contact_level(self, on_relative: float | None) -> None:
        """Set the contact-on level, in relative units of the rest light (None: the calibrated one).

        The off and truncation levels are lowered to it if they were higher.
        Kept across a tare.
        """
        if on_relative is not None and not on_relative > 0:
            raise ValueError(f"contact level must be > 0, got {on_relative!r}")
        self.levels.on_override = on_relative
        if self.baseline.ready:
            self._levels_changed()

    def reset_baseline(self, frames: int | None = None) -> None:
        """Tare: re-baseline from the next ``frames`` frames (default: the bundle's ``baseline_frames``)."""
        self.baseline.reset(frames)
        self.bright_fibers.reset()
        self._in_contact = False
        self._contact_end_ns = None
        self.motion.reset()
        self.vibration.reset()
        if self.gain_compensation is not None:
            self.gain_compensation.reset_gain(self.gain_compensation.reference_ns)
        if self.kernel is not None:
            self.kernel.kernel.reset_contact()
            self.kernel.reset_gain(self.kernel.kernel.reference_ns)

    def _levels_changed(self) -> None:
        levels = self.levels
        levels.update(self.baseline.values, self._live)
        if self.gain_compensation is not None:
            self.gain_compensation.set_levels(levels.gain_delta, levels.gain_tolerance, levels.gain_significant)
        if self.kernel is not None:
            self.kernel.kernel.set_levels(levels.trunc, levels.off, levels.on, levels.gain_delta,
                                          levels.gain_tolerance, levels.gain_significant)

    def set_corrector(self, corrector: ContactCorrector | None) -> None:
        """Apply ``corrector`` (the bundle's calibration models) to every contact; None: raw estimates.

        By default the bundle's own models are applied (numpy shape evaluator).
        """
        self.corrector = corrector if corrector is not None and corrector.active else None
        #: The kernel applies the corrector's models (else they run here, per contact).
        self._kernel_corrects = self.kernel is not None and self.kernel.use_corrector(self.corrector)
        # centroid and width calibrations are applied to the estimates
        self.result.calibrated = self.corrector is not None and self.corrector.calibrated

    # -- per frame -------------------------------------------------------------

    def process(self, frame: np.ndarray, now_ns: int, saturated: bool = False, *,
                means_ready: bool = False) -> FrameResult:
        """Everything one frame gives.

        Parameters
        ----------
        frame : ndarray, uint8
            A checked frame (:class:`~optitac_edge.core.frame_check.FrameCheck`, or
            :meth:`FiberTable.check_frame <optitac_edge.core.fiber_table.FiberTable.check_frame>` for a
            recording): C-contiguous, of the bundle's size and pixel format (gray (H, W), rgb (H, W, 3)
            or yuv420 (H*3//2, W)); not checked again.
        now_ns : int
            Timestamp of the frame, ns (copied to ``t_ns``; the baseline tracking's clock).
        saturated : bool
            The frame check found a live fiber centre at full scale (carried into the result).
        means_ready : bool
            The kernel's check (:func:`process_checked`) took this frame's fiber means already.

        Returns
        -------
        FrameResult
            The pipeline's reused result, updated in place: the contacts with their ids, the releases
            and the frame's flags.
        """
        result, est, fk = self.result, self._estimate, self.kernel
        result.saturated = saturated
        result.light_changed = result.baseline_raised = False
        est.frame, est.t_ns = self._frame, now_ns
        self._frame += 1
        dt_ns = 0 if self._last_ns is None else now_ns - self._last_ns
        self.after_gap = dt_ns > self._gap_ns
        if self.after_gap:
            self._forget(now_ns)
            dt_ns = 0  # no baseline tracking step across the gap
        self._last_ns = now_ns
        baseline, gain = self.baseline, self.gain_compensation
        if fk is not None and baseline.ready:  # steps 2-10 in the kernel
            est.baseline_ready = True
            n = fk.run(frame, now_ns, dt_ns, est, self.contacts, None if self._kernel_corrects else self.corrector,
                       means_ready)
            result.light_changed = gain is not None and fk.light_changed
            _track(self, n, now_ns, dt_ns)
            if fk.raise_pending:
                self._raise(fk.rest, fk.common)
            return result
        means = self.sampler.means(frame, self._means) if fk is None else fk.means(frame, self._means)
        if not baseline.ready:
            if baseline.add(means):
                self._levels_changed()
                for g in (gain, fk):
                    if g is not None:
                        g.reset_gain(now_ns)
            est.baseline_ready = False
            est.clear()
            _track(self, 0, now_ns, None)
            return result
        est.baseline_ready = True
        signal = self.compute_signal(means, now_ns)
        result.light_changed = gain is not None and gain.light_changed
        surface = self.surface_op.compute(signal, self._surface, self.levels.trunc)
        n = self.finder.find(surface, est, self._in_contact, self.corrector, self._gated(signal))
        _track(self, n, now_ns, dt_ns)
        self._follow_light(n, means, signal, now_ns, dt_ns)
        return result

    def _gated(self, signal: np.ndarray) -> bool:
        """With neighbour support: the frame's supported peak stays below the level (no contact)."""
        if self.support is None:
            return False
        level = self.levels.off if self._in_contact else self.levels.on
        return not self.support.peak(signal) > float(level)

    def _forget(self, now_ns: int) -> None:
        """A gap: what the frames before it left (hysteresis, motion, the vibration filter, the bright-fiber
        timer) is dropped; the tracker releases their contacts with this frame (``after_gap``)."""
        self._in_contact = False
        self._contact_end_ns = None
        self.bright_fibers.reset()
        self.motion.reset()
        self.vibration.reset()
        if self.kernel is not None:
            self.kernel.kernel.reset_contact()

    def _raise(self, rest: np.ndarray, common: float) -> None:
        """Step 10's action: the fibers brighter than their baseline raised to ``rest``, the levels after."""
        self.result.raised_fibers = self.baseline.raise_to(rest, self._signal, float(self.levels.off), common)
        self._levels_changed()
        self.result.baseline_raised = True

    def _follow_light(self, n: int, means: np.ndarray, signal: np.ndarray, now_ns: int, dt_ns: int) -> None:
        """Steps 9 and 10 after a frame with ``n`` contacts: a baseline taken over a press raised, else the
        baseline and the LED gain follow the light of contact-free frames."""
        baseline, gain = self.baseline, self.gain_compensation
        if n > 0:
            self._in_contact = True
        elif self._in_contact:
            self._in_contact = False
            self._contact_end_ns = now_ns
        if self.bright_fibers.check(signal, float(self.levels.off), now_ns, n == 0):
            self._raise(_rest_light(means, gain, baseline), self.bright_fibers.common)
            return
        if n == 0 and gain is not None:
            gain.contact_free(now_ns)
        if n == 0 and self.options.track_baseline and dt_ns > 0:
            baseline.track(_rest_light(means, self.gain_compensation, baseline), signal, float(self.levels.off), now_ns, dt_ns,
                           self._contact_end_ns)

    def adopt_tracking(self, previous: Pipeline) -> None:
        """Go on with ``previous``'s contact ids (a re-oriented bundle replacing it): its contacts are
        released by this pipeline's first frame, and no id is handed out again at once."""
        self.tracker = previous.tracker
        self.motion = previous.motion
        self.vibration.period_s = previous.vibration.period_s
        self.result.released = self.tracker.released

    def compute_signal(self, means: np.ndarray, now_ns: int) -> np.ndarray:
        """Step 4: the inverted signal of ``means`` (shape (N,)) into :attr:`signal` (see there)."""
        gain = self.gain_compensation
        if gain is not None:
            signal = gain.signal(means, self.baseline, now_ns, self._signal)
        else:
            signal = np.subtract(self.baseline.values, means, out=self._signal)
            if self.options.relative:
                np.multiply(signal, self.baseline.inv_level, out=signal)
        if self._has_dead:
            signal[self._dead] = 0.0
        if self.levels.bands is not None:  # each fiber's band (core/levels.py)
            banded(signal, self.levels.bands, self._clipped, self._band_work)
        return signal


def process_checked(pipe: Pipeline, frame: np.ndarray, now_ns: int, check: FrameCheck) -> FrameResult | str:
    """``pipe.process`` of a frame that passes ``check``, else why not (``"dark"``, ``"saturated"``).

    ``frame`` must have passed :meth:`FrameCheck.bad <optitac_edge.core.frame_check.FrameCheck.bad>`.
    With the compiled kernel (baseline ready) the check reads its pixels after the fiber means, once
    the frame is in the caches; otherwise ``check`` runs first. A frame refused changes nothing.
    """
    fk = pipe.kernel
    if fk is not None and pipe.baseline.ready:
        why = fk.check(frame)
        return why if why is not None else pipe.process(frame, now_ns, fk.saturated, means_ready=True)
    why = check(frame)
    return why if why is not None else pipe.process(frame, now_ns, check.saturated)
