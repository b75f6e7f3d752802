"""The runtime pipeline: camera frame -> :class:`ContactEstimate`, per frame.

Per frame (the OptiTac method, see :mod:`optitac_edge.devtools.reference` for the
literal version, and :class:`~optitac_edge.core.bundle.ContactOptions` for the
switchable improvements beyond the paper noted in brackets):

1. :meth:`Pipeline.process` checks the frame against the bundle: shape, dtype,
   pixel format, dark or saturated (:class:`~optitac_edge.core.frame_check.FrameCheck`;
   the compiled kernel reads the same pixels after the fiber means), and skips
   it with a :class:`~optitac_edge.core.frame_engine.Skip`; a recording's frames,
   checked once, go to :meth:`Pipeline.process_recorded`, every one processed;
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

Steps 2 to 10 run in a :class:`~optitac_edge.core.frame_engine.FrameEngine`: the
numpy parts (:class:`~optitac_edge.core.numpy_engine.NumpyEngine`, the readable
reference, each step a named part the benchmark times alone) or the compiled
kernel on the same buffers (:class:`~optitac_edge.core.compiled.CompiledEngine`).
The pipeline owns what the two share: the :class:`~optitac_edge.core.baseline.Baseline`
(3, 9), the :class:`~optitac_edge.core.levels.ContactLevels`, the
:class:`~optitac_edge.core.corrections.ContactCorrector` (the calibration
models), the :class:`~optitac_edge.core.tracking.ContactTracker` (8), the motion
and vibration (8b), the raise of step 10 and the result.

All buffers are allocated at construction; a frame allocates nothing that
outlives it (net 0 bytes per frame after warm-up, measured by
``optitac-edge bench``), only small temporaries: scalars, OpenCV's moment
dictionaries, and the partition's labels and counts when several contacts
are allowed and a frame has more than one blob or seed.
numpy and OpenCV only; see docs/performance.md.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from contextlib import contextmanager

import cv2
import numpy as np

from optitac_edge.core.baseline import Baseline
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.compiled import CompiledEngine, kernel_status
from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.corrections import ContactCorrector
from optitac_edge.core.fingerprint import SensorCheck, SensorFit, SensorMismatchError
from optitac_edge.core.frame_engine import FrameEngine, Skip
from optitac_edge.core.frame_result import FrameResult
from optitac_edge.core.gain import LedGain
from optitac_edge.core.levels import ContactLevels, FiberModel
from optitac_edge.core.numpy_engine import NumpyEngine
from optitac_edge.core.options import MAX_CONTACTS, ContactOptions
from optitac_edge.core.tracking import GATE_PITCH, ContactTracker
from optitac_edge.errors import PipelineBusy


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


_BUSY = ("this Pipeline is processing a frame in another thread: a pipeline serves one thread "
         "(one pipeline per thread, or a lock around it)")


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
                 compiled: bool | None = None, fps: float | None = None, source: str = "the frames") -> None:
        self.bundle = bundle
        #: The first baseline's frames checked against the bundle's sensor (None once they fitted).
        self._sensor_check: SensorCheck | None = SensorCheck(bundle, source)
        #: Why the frames are not of the bundle's sensor (every later frame raises it), or None.
        self.mismatch: SensorMismatchError | None = None
        #: How the first baseline's frames fitted the bundle's fiber map (None before).
        self.sensor_fit: SensorFit | None = None
        self.options = o = bundle.options if options is None else options
        #: Step 3 and 9: the rest light, averaged then tracked.
        self.baseline = Baseline(bundle.fibers.n_fibers, bundle.baseline_frames, o.black_level, o.baseline_tau_s,
                                 o.holdoff_s)
        #: The truncation, off and on levels.
        self.levels = ContactLevels(o, bundle.thresholds.threshold, FiberModel(bundle))
        self._n, self._frame = bundle.grid.n, 0
        self._last_ns: int | None = None
        self._gap_ns = round(o.gap_s * 1e9)
        #: The last frame followed a gap longer than ``options.gap_s``: it was processed as a snapshot.
        self.after_gap = False
        #: All contacts of the last frame, valid ``[:n_contacts]``, strongest first.
        self.contacts: list[ContactEstimate] = [ContactEstimate() for _ in range(MAX_CONTACTS)]
        self._estimate = self.contacts[0]
        #: The numpy parts of steps 2-10 (their buffers are the pipeline's, whichever engine runs).
        self.parts = NumpyEngine(bundle, o, self.baseline, self.levels, self.contacts)
        own = ContactCorrector(bundle)
        #: Per-contact corrections (centroid error map, width model, shape), or None.
        self.corrector: ContactCorrector | None = own if own.active else None
        #: What runs steps 2-10: the compiled kernel when it is built (or asked for; it applies the bundle's
        #: own models itself), else the numpy parts.
        self.engine: FrameEngine = (CompiledEngine(self.parts, self.corrector)
                                    if compiled or (compiled is None and kernel_status()[0]) else self.parts)
        #: Stable contact ids, touch frames and releases from frame to frame.
        self.tracker = ContactTracker(GATE_PITCH * bundle.layout.pitch_mm, max_contacts=MAX_CONTACTS)
        #: What the last frame gave (the object :meth:`process` returns, updated in place).
        self.result = FrameResult(self.contacts, self.tracker.released)
        #: Held while a frame is processed: a second thread's frame meanwhile is refused (PipelineBusy).
        self._in_use = threading.Lock()
        self.set_corrector(self.corrector)
        #: Step 8b: every contact's velocity and slip state, and the fibers' vibration.
        self.motion, self.vibration = self.engine.motion_parts()
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
    def compiled(self) -> bool:
        """The compiled kernel runs the frames."""
        return self.engine is not self.parts

    @property
    def baseline_ready(self) -> bool:
        return self.baseline.ready

    @property
    def means(self) -> np.ndarray:
        """The last frame's fiber means, shape (N,), float32 (gray levels)."""
        return self.parts.means_buf

    @property
    def surface(self) -> np.ndarray:
        """The last truncated inverted surface, shape (n, n), float32, signal units.

        Truncated at the truncation level (gray levels, or relative units with
        ``options.relative``). A view into the pipeline's buffer (overwritten by
        the next frame).
        """
        return self.parts.surface_buf.reshape(self._n, self._n)

    def surface_levels(self) -> np.ndarray:
        """The last surface in units of the level it is truncated at, shape (n, n), float32 (a new array): the
        public API's ``Reading.surface`` and the tactile image of ``export-lerobot --video``."""
        return self.surface / np.float32(self.levels.trunc or 1.0)

    @property
    def signal(self) -> np.ndarray:
        """The last inverted per-fiber signal, shape (N,), float32.

        ``baseline - mean`` (gray levels), or divided by ``baseline - black_level``
        with ``options.relative``; with ``options.compensate_gain`` the mean's
        light above the black level is divided by :attr:`gain` first; 0 for
        dead fibers.
        """
        return self.parts.signal_buf

    @property
    def led_gain(self) -> LedGain | None:
        """The LED gain compensation's state after the last frame (``.gain``: the gain relative to the
        baseline the frame was compensated with); None without ``compensate_gain``."""
        return self.engine.led_gain()

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
        self.engine.reset_contact()
        self.motion.reset()
        self.vibration.reset()
        self.engine.reset_gain(None)

    def _levels_changed(self) -> None:
        self.levels.update(self.baseline.values, self.parts.live)
        self.engine.set_levels(self.levels)

    def set_corrector(self, corrector: ContactCorrector | None) -> None:
        """Apply ``corrector`` (the bundle's calibration models) to every contact; None: raw estimates.

        By default the bundle's own models are applied (numpy shape evaluator).
        """
        self.corrector = corrector if corrector is not None and corrector.active else None
        self.engine.use_corrector(self.corrector)
        # centroid and width calibrations are applied to the estimates
        self.result.calibrated = self.corrector is not None and self.corrector.calibrated

    # -- per frame -------------------------------------------------------------

    def process(self, frame: object, now_ns: int) -> FrameResult | Skip:
        """Everything one camera frame gives, or why it was skipped.

        Parameters
        ----------
        frame : ndarray, uint8
            A camera frame, of the bundle's size and pixel format (gray (H, W), rgb (H, W, 3) or yuv420
            (H*3//2, W)), C-contiguous.
        now_ns : int
            Timestamp of the frame, ns (copied to ``t_ns``; the baseline tracking's clock).

        Returns
        -------
        FrameResult or Skip
            The pipeline's reused result, updated in place: the contacts with their ids, the releases and the
            frame's flags (``saturated``: a live fiber centre at full scale); or why the frame was skipped
            (not a frame of this camera, dark, saturated), when nothing changes.

        Raises
        ------
        PipelineBusy
            Another thread's frame is in this pipeline (it serves one thread; nothing changes).
        """
        if not self._in_use.acquire(blocking=False):
            raise PipelineBusy(_BUSY)
        try:
            if self.mismatch is not None:
                raise self.mismatch
            engine = self.engine
            why = engine.check(frame)
            if why is not None:
                return why
            assert isinstance(frame, np.ndarray)  # the check refuses anything else
            return self._step(frame, now_ns, engine.saturated)
        finally:
            self._in_use.release()

    def process_recorded(self, frame: np.ndarray, now_ns: int) -> FrameResult:
        """Everything one frame of a recording gives: as :meth:`process`, with no frame skipped (a recording's
        frames are checked once, :meth:`FiberTable.check_frame
        <optitac_edge.core.fiber_table.FiberTable.check_frame>`, and each frame has its row).

        Raises
        ------
        PipelineBusy
            Another thread's frame is in this pipeline.
        """
        if not self._in_use.acquire(blocking=False):
            raise PipelineBusy(_BUSY)
        try:
            if self.mismatch is not None:
                raise self.mismatch
            return self._step(frame, now_ns, False)
        finally:
            self._in_use.release()

    def _step(self, frame: np.ndarray, now_ns: int, saturated: bool) -> FrameResult:
        result, est, engine, baseline = self.result, self._estimate, self.engine, self.baseline
        result.saturated = saturated
        result.light_changed = result.baseline_raised = False
        result.frame, result.t_ns = self._frame, now_ns
        self._frame += 1
        dt_ns = 0 if self._last_ns is None else now_ns - self._last_ns
        self.after_gap = dt_ns > self._gap_ns
        if self.after_gap:
            self._forget()
            dt_ns = 0  # no baseline tracking step across the gap
        self._last_ns = now_ns
        if not baseline.ready:
            engine.means(frame)
            check = self._sensor_check
            if check is not None:
                check.add(frame)
            if baseline.add(self.means):
                if check is not None:
                    self._confirm_sensor(check)
                self._levels_changed()
                engine.reset_gain(now_ns)
            result.baseline_ready = False
            est.clear()
            self._track(0, now_ns, None)
            return result
        result.baseline_ready = True
        n = engine.run(frame, now_ns, dt_ns)
        result.light_changed = engine.light_changed
        self._track(n, now_ns, dt_ns)
        if engine.raise_pending:
            self._raise(engine.rest, engine.common)
        return result

    def name_source(self, source: str) -> None:
        """What the frames come from (a recording's path, a camera), for the line that refuses them when they
        are not of the bundle's sensor."""
        if self._sensor_check is not None:
            self._sensor_check.source = source

    def _confirm_sensor(self, check: SensorCheck) -> None:
        """The first baseline is complete: its frames must be of the bundle's sensor
        (:mod:`~optitac_edge.core.fingerprint`); else the baseline is dropped and this and every later frame
        raise :class:`~optitac_edge.core.fingerprint.SensorMismatchError`."""
        self._sensor_check = None
        try:
            self.sensor_fit = check.finish()
        except SensorMismatchError as exc:
            self.baseline.reset()
            self.mismatch = exc
            raise

    def _track(self, n: int, now_ns: int, dt_ns: int | None) -> None:
        """Steps 8 and 8b: ids, touches and releases of the frame's ``n`` contacts into the result; then
        (``dt_ns`` given: the baseline is ready) their motion and the frame's vibration."""
        result = self.result
        self.tracker.update(result.contacts, n, result.frame, self.after_gap)
        result.n_contacts = n
        result.n_released = self.tracker.n_released
        if dt_ns is None:
            result.vibration, result.vibrating, result.vibration_began = math.nan, False, False
            return
        self.motion.update(result.contacts, n, result.frame, now_ns)
        meter = self.vibration
        result.vibration = meter.update(float(self.levels.trunc), dt_ns)
        result.vibrating, result.vibration_began = meter.vibrating, meter.began

    def _forget(self) -> None:
        """A gap: what the frames before it left (hysteresis, motion, the vibration filter, the bright-fiber
        timer) is dropped; the tracker releases their contacts with this frame (``after_gap``)."""
        self.engine.reset_contact()
        self.motion.reset()
        self.vibration.reset()

    def _raise(self, rest: np.ndarray, common: float) -> None:
        """Step 10's action: the fibers brighter than their baseline raised to ``rest``, the levels after."""
        self.result.raised_fibers = self.baseline.raise_to(rest, self.signal, float(self.levels.off), common)
        self._levels_changed()
        self.result.baseline_raised = True

    def adopt_tracking(self, previous: Pipeline) -> None:
        """Go on with ``previous``'s contact ids (a re-oriented bundle replacing it): its contacts are
        released by this pipeline's first frame, and no id is handed out again at once."""
        self.tracker = previous.tracker
        self.motion = previous.motion
        self.vibration.period_s = previous.vibration.period_s
        self.result.released = self.tracker.released
