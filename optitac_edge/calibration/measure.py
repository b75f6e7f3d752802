"""Run the pipeline over a whole recording and keep every frame's estimate as arrays."""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.corrections import ContactCorrector
from optitac_edge.core.fingerprint import describe_bundle
from optitac_edge.core.frame_result import FrameResult
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.errors import FrameMismatchError, RecordingError
from optitac_edge.io.recording import Recording, Truth


@dataclass(frozen=True, eq=False)
class Measurements:
    """Per-frame estimates of one recording; NaN / '' where no contact.

    Attributes
    ----------
    contact : ndarray, shape (N,), bool
    x_mm, y_mm, major_mm, minor_mm, angle_deg, strength, area_mm2, peak : ndarray, shape (N,), float64
    hu : ndarray, shape (N, 7), float64
        Log-Hu features of the primary contact.
    features : ndarray, shape (N, F), float64
        The shape classifier's input of the primary contact (log-Hu and q4).
    shape : ndarray, shape (N,), str
    confidence : ndarray, shape (N,), float64
    depth_mm, force_n : ndarray, shape (N,), float64, optional
        The bundle's depth and force model (NaN when not calibrated); None: not read.
    motion : FrameMotion, optional
        The primary contact's id, velocity and slip state and the frame's vibration; None: not read.
    """

    contact: np.ndarray
    x_mm: np.ndarray
    y_mm: np.ndarray
    major_mm: np.ndarray
    minor_mm: np.ndarray
    angle_deg: np.ndarray
    strength: np.ndarray
    area_mm2: np.ndarray
    peak: np.ndarray
    hu: np.ndarray
    features: np.ndarray
    shape: np.ndarray
    confidence: np.ndarray
    depth_mm: np.ndarray | None = None
    force_n: np.ndarray | None = None
    motion: FrameMotion | None = None

    def __len__(self) -> int:
        return int(self.contact.shape[0])


@dataclass(frozen=True, eq=False)
class FrameMotion:
    """Per frame: the primary contact's motion and the frame's vibration (arrays of shape (N,)).

    Attributes
    ----------
    contact_id, slide_frame : ndarray, int64
        0 / -1 without contact or while held.
    vx_mm_s, vy_mm_s, vibration : ndarray, float64
    sliding, vibrating, vibration_began : ndarray, bool
    """

    contact_id: np.ndarray
    vx_mm_s: np.ndarray
    vy_mm_s: np.ndarray
    sliding: np.ndarray
    slide_frame: np.ndarray
    vibration: np.ndarray
    vibrating: np.ndarray
    vibration_began: np.ndarray

    @classmethod
    def empty(cls, n: int) -> FrameMotion:
        return cls(np.zeros(n, np.int64), np.full(n, np.nan), np.full(n, np.nan), np.zeros(n, bool),
                   np.full(n, -1, np.int64), np.full(n, np.nan), np.zeros(n, bool), np.zeros(n, bool))

    def record(self, i: int, est: ContactEstimate, result: FrameResult) -> None:
        """Frame ``i``'s values from its primary estimate and result."""
        self.contact_id[i], self.slide_frame[i] = est.contact_id, est.slide_frame
        self.vx_mm_s[i], self.vy_mm_s[i], self.sliding[i] = est.vx_mm_s, est.vy_mm_s, est.sliding
        self.vibration[i], self.vibrating[i] = result.vibration, result.vibrating
        self.vibration_began[i] = result.vibration_began


#: Where no progress bar is shown (the output is not a terminal), a line this often, s.
PROGRESS_S = 5.0
#: Progress lines of long steps (the command line shows them unless -q, docs: its log level).
progress_log = logging.getLogger("optitac_edge.progress")


def replay_recording(rec: Recording, pipeline: Pipeline, progress: bool | None = None,
                     desc: str = "replay") -> Iterator[tuple[int, FrameResult]]:
    """Every frame of ``rec`` through ``pipeline`` at its capture time (``rec.t_ns``; ``i / fps`` when not stamped).

    Yields ``(frame index, result)``; the result is the pipeline's reused
    object (copy what you keep). The baseline comes from the leading rest frames, and is taken again at
    each of the recording's tare points (``rec.tares``).

    Parameters
    ----------
    progress : bool, optional
        Show a progress bar on stderr (default: when stderr is a terminal).

    Raises
    ------
    FrameMismatchError
        If the recording's frames are not what the pipeline's bundle was built for: their size or pixel
        format, or (:class:`~optitac_edge.core.fingerprint.SensorMismatchError`, at the end of the first
        baseline) another sensor's.
    """
    from tqdm import tqdm

    try:
        pipeline.bundle.fibers.check_frame(rec.frames[0], rec.pixel_format)
    except FrameMismatchError as exc:
        raise FrameMismatchError(f"{rec.path}: {exc} ({describe_bundle(pipeline.bundle)})") from None
    pipeline.name_source(f"{rec.path}'s frames")
    t_ns = rec.t_ns
    tares = {t.frame: t.frames for t in rec.tares}
    show = sys.stderr.isatty() if progress is None else progress
    said = time.monotonic()
    for i in tqdm(range(len(rec)), desc=desc, unit="frame", disable=not show, leave=False):
        if not show and i % 64 == 0 and time.monotonic() - said >= PROGRESS_S:  # a log line where no bar is
            said = time.monotonic()
            progress_log.info("%s: frame %d of %d (%.0f %%)", desc, i, len(rec), 100 * i / len(rec))
        if i in tares:
            pipeline.reset_baseline(tares[i])
        yield i, pipeline.process_recorded(rec.frames[i], int(t_ns[i]))


def measure_recording(rec: Recording, bundle: CalibrationBundle, corrected: bool = True,
                      progress: bool | None = None, shape_backend: str = "numpy",
                      onnx_path: str | None = None) -> Measurements:
    """Process every frame of ``rec``; the baseline comes from its leading rest frames.

    Parameters
    ----------
    corrected : bool
        Apply the bundle's calibration models (centroid map, width model, shape
        classifier); False gives the raw method's estimates, as fitted by the
        calibration steps.
    progress : bool, optional
        Show a progress bar (default: when stderr is a terminal).
    shape_backend, onnx_path
        How the shape model is evaluated (see :class:`~optitac_edge.core.corrections.ContactCorrector`).
    """
    pipeline = Pipeline(bundle, fps=rec.meta.fps)
    pipeline.set_corrector(ContactCorrector(bundle, shape_backend, onnx_path) if corrected else None)
    n = len(rec)
    cols = {k: np.full(n, np.nan) for k in ("x_mm", "y_mm", "major_mm", "minor_mm", "angle_deg",
                                            "strength", "area_mm2", "peak", "confidence", "depth_mm",
                                            "force_n")}
    contact = np.zeros(n, dtype=bool)
    hu = np.full((n, 7), np.nan)
    features = np.full((n, pipeline.contacts[0].features.size), np.nan)
    shape = np.full(n, "", dtype=object)
    motion = FrameMotion.empty(n)
    for i, result in replay_recording(rec, pipeline, progress, desc=f"measure {rec.path.name}"):
        est = result.primary
        motion.record(i, est, result)
        if not est.contact:
            continue
        contact[i] = True
        for k, col in cols.items():
            col[i] = getattr(est, k)
        hu[i] = est.hu
        features[i] = est.features
        shape[i] = est.shape
    return Measurements(contact=contact, hu=hu, features=features, shape=shape.astype(str), motion=motion, **cols)


def recordings_named(recs: Sequence[Recording]) -> str:
    """The recordings' paths, for a line a person reads."""
    return ", ".join(str(r.path) for r in recs)


def measure_sessions(recs: Sequence[Recording], bundle: CalibrationBundle, corrected: bool = True,
                     progress: bool | None = None, shape_backend: str = "numpy",
                     onnx_path: str | None = None) -> tuple[Measurements, Truth]:
    """Several recordings (days, sessions) measured as one, each with its own baseline (its rest frames and
    tare points) and a pipeline of its own, then joined: frames numbered on from one recording to the next,
    every truth row with its recording's number (``Truth.session``: a press never spans two).

    Raises
    ------
    RecordingError
        When a recording has no truth.csv.
    """
    if not recs:
        raise RecordingError("no recordings given")
    parts, truths, offset = [], [], 0
    for k, rec in enumerate(recs):
        if rec.truth is None:
            raise RecordingError(f"{rec.path}: needs truth.csv")
        parts.append(measure_recording(rec, bundle, corrected, progress, shape_backend, onnx_path))
        truths.append((rec.truth, offset, k))
        offset += len(rec)
    return join_measurements(parts), join_truths(truths)


def join_measurements(parts: Sequence[Measurements]) -> Measurements:
    """Measurements of several recordings, one after the other."""
    if len(parts) == 1:
        return parts[0]
    values: dict[str, Any] = {}
    for f in fields(Measurements):
        got = [getattr(p, f.name) for p in parts]
        if f.name == "motion":
            values[f.name] = None if any(g is None for g in got) else FrameMotion(
                *(np.concatenate([getattr(g, h.name) for g in got]) for h in fields(FrameMotion)))
        elif any(g is None for g in got):
            values[f.name] = None
        else:
            values[f.name] = np.concatenate(got)
    return Measurements(**values)


def join_truths(parts: Sequence[tuple[Truth, int, int]]) -> Truth:
    """The truths of several recordings as one: each ``(truth, its first frame's number, its session)``."""
    if len(parts) == 1 and parts[0][1] == 0:
        return parts[0][0]
    n = [len(t) for t, _, _ in parts]

    def column(name: str, fill: object) -> np.ndarray | None:
        got = [getattr(t, name) for t, _, _ in parts]
        if all(g is None for g in got):
            return None
        return np.concatenate([np.full(k, fill) if g is None else g for g, k in zip(got, n)])

    frame = np.concatenate([t.frame + offset for t, offset, _ in parts])
    session = np.concatenate([np.full(len(t), k, dtype=np.int64) for t, _, k in parts])
    required = {name: np.concatenate([getattr(t, name) for t, _, _ in parts])
                for name in ("contact", "shape", "x_mm", "y_mm", "angle_deg", "size_mm", "depth_mm")}
    motion = column("motion", "")
    return Truth(frame=frame, **required, force_n=column("force_n", np.nan), vx_mm_s=column("vx_mm_s", np.nan),
                 vy_mm_s=column("vy_mm_s", np.nan), motion=None if motion is None else motion.astype(str),
                 session=session)


def fiber_signals(recs: Sequence[Recording], bundle: CalibrationBundle, progress: bool | None = None
                  ) -> tuple[np.ndarray, np.ndarray, Truth, np.ndarray]:
    """Every truth row's per-fiber signal (relative to the baseline, the LED gain divided out, no fiber's band:
    what each fiber's band and the levels are chosen from), each recording with its own baseline.

    Returns
    -------
    signals : ndarray, shape (rows, N), float64
        NaN on a row whose frame came while the baseline was being taken (the leading rest frames, a tare).
    light : ndarray, shape (rows, N), float64
        Each fiber's rest light above black in the baseline the row was measured against, gray levels.
    truth : Truth
        The recordings' truth rows joined (:func:`measure_sessions`).
    t_ns : ndarray, shape (rows,), int64
        Each row's frame time.
    """
    plain = bundle.with_updates(extra_arrays={k: v for k, v in bundle.extra_arrays.items()
                                              if not k.startswith("levels/")})
    rows, lights, truths, times, offset = [], [], [], [], 0
    for k, rec in enumerate(recs):
        if rec.truth is None:
            raise RecordingError(f"{rec.path}: needs truth.csv")
        times.append(rec.t_ns[rec.truth.frame])
        pipeline = Pipeline(plain)
        pipeline.set_corrector(None)
        wanted = {int(f): j for j, f in enumerate(rec.truth.frame)}
        got = np.full((len(rec.truth), bundle.layout.n_fibers), np.nan)
        light = np.ones_like(got)
        for i, result in replay_recording(rec, pipeline, progress, desc=f"signals {rec.path.name}"):
            j = wanted.get(i)
            if j is not None and result.baseline_ready:
                got[j] = pipeline.signal
                light[j] = pipeline.baseline.level
        rows.append(got)
        lights.append(light)
        truths.append((rec.truth, offset, k))
        offset += len(rec)
    return np.concatenate(rows), np.concatenate(lights), join_truths(truths), np.concatenate(times)
