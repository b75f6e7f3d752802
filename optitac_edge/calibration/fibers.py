"""Fiber calibration: rest frames in, a complete calibration bundle out."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from optitac_edge.core.bundle import BASELINE_FRAMES, CalibrationBundle
from optitac_edge.core.fiber_table import FiberSampler, FiberTable
from optitac_edge.core.fingerprint import FINGERPRINT_KEY, fingerprint_meta
from optitac_edge.core.frames import frame_geometry, to_gray
from optitac_edge.core.grid import SurfaceGrid
from optitac_edge.core.layout import FiberLayout, hex_layout
from optitac_edge.core.levels import LEVELS_KEY, NOISE_KEY
from optitac_edge.core.options import ContactOptions, ContactThresholds
from optitac_edge.errors import FiberMapError
from optitac_edge.text import fields

log = logging.getLogger(__name__)


def _jsonable(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        obj = dataclasses.asdict(obj)
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def calibrate_fibers(
    rest_frames: Sequence[np.ndarray] | np.ndarray,
    pixel_format: str,
    layout: FiberLayout | None = None,
    rotation_hint_deg: float = 0.0,
    mirror: bool = False,
    thresholds: ContactThresholds | None = None,
    options: ContactOptions | None = None,
    times_ns: np.ndarray | None = None,
) -> CalibrationBundle:
    """Build a calibration bundle from contact-free frames.

    Parameters
    ----------
    rest_frames : sequence of ndarray, uint8
        At least one contact-free frame in ``pixel_format``; all the same size.
    pixel_format : str
        ``gray``, ``rgb`` or ``yuv420``.
    layout : FiberLayout, optional
        The sensor's CAD layout; the default 217-fiber hexagonal layout if None.
    rotation_hint_deg, mirror
        Orientation hint (see docs/formats.md); the hint must be within 20 degrees.
    thresholds : ContactThresholds, optional
        Contact thresholds to store (default: :meth:`ContactThresholds.for_pitch` of the layout's pitch).
    options : ContactOptions, optional
        Contact options to store (default: ``ContactOptions()``); their
        measured fields (``noise_rel``, ``noise_gray``, ``black_level``) are
        replaced by what the rest frames show (see :func:`measure_rest_noise`).
    times_ns : ndarray, shape (F,), int64, optional
        The rest frames' capture times: only frames within ``options.gap_s`` of each other tell the
        frame-to-frame noise (default: all consecutive frames do).

    Raises
    ------
    FiberMapError
        If the fibers cannot be found reliably.
    """
    from optitac_edge.calibration.fiber_map import build_fiber_map
    from optitac_edge.calibration.interpolation import build_interpolation

    layout = hex_layout() if layout is None else layout
    if len(rest_frames) == 0:
        raise FiberMapError("no rest frames to calibrate from")
    h, w = frame_geometry(rest_frames[0].shape, pixel_format)
    gray = np.stack([to_gray(np.asarray(f), pixel_format) for f in rest_frames])
    result = build_fiber_map(gray, layout, rotation_hint_deg=rotation_hint_deg, mirror=mirror,
                             pixel_format=pixel_format)
    grid = SurfaceGrid.for_layout(layout)
    matrix, factors = build_interpolation(layout, grid)
    report = _jsonable(result.report)
    log.info("fiber calibration of %dx%d %s frames: %s", w, h, pixel_format, fields(report))
    options = options or ContactOptions()
    gap_ns = None if times_ns is None else round(options.gap_s * 1e9)
    noise = measure_rest_noise(rest_frames, result.table, gray.mean(axis=0), times_ns=times_ns, gap_ns=gap_ns)
    log.info("rest noise: %s", fields(noise.summary()))
    options = dataclasses.replace(options, noise_rel=noise.noise_rel, noise_gray=noise.noise_gray,
                                  black_level=noise.black_level)
    bundle = CalibrationBundle(
        layout=layout, transform=result.transform, fibers=result.table, grid=grid,
        interpolation=matrix, thresholds=thresholds or ContactThresholds.for_pitch(layout.pitch_mm), options=options,
        fiber_map_report=report, surface_factors=factors,
        extra_arrays={NOISE_KEY: noise.fiber_noise} if noise.samples >= 2 else {},
        extra_meta={LEVELS_KEY: {"noise_samples": noise.samples, "noise_between_snapshots": noise.between_snapshots}}
        if noise.samples >= 2 else {},
    )
    if layout.fiducial is not None and np.any(layout.fiducial):
        bundle = _orient_by_fiducials(bundle, rest_frames)
    return with_fingerprint(bundle, rest_frames)


def with_fingerprint(bundle: CalibrationBundle, rest_frames: Sequence[np.ndarray] | np.ndarray) -> CalibrationBundle:
    """``bundle`` with its sensor's fingerprint from ``rest_frames`` (:func:`~optitac_edge.core.fingerprint.
    fingerprint_meta`): what every consumer checks frames against."""
    meta = dict(bundle.extra_meta)
    meta[FINGERPRINT_KEY] = fingerprint_meta(bundle, rest_frames)
    return bundle.with_updates(extra_meta=meta)


def _orient_by_fiducials(bundle: CalibrationBundle, rest_frames: Sequence[np.ndarray] | np.ndarray
                         ) -> CalibrationBundle:
    """Settle the layout's symmetry from fibers dark or bright by design (see :func:`fiducial_orientation`)."""
    from optitac_edge.calibration.orientation import (
        fiducial_orientation,
        layout_symmetries,
        reorient_bundle,
    )

    sampler = FiberSampler(bundle.fibers)
    out = np.empty(bundle.layout.n_fibers, dtype=np.float32)
    levels = np.mean([sampler.means(np.ascontiguousarray(f), out).copy() for f in rest_frames], axis=0)
    levels[bundle.fibers.dead] = 0.0
    fit = fiducial_orientation(levels, bundle.layout, layout_symmetries(bundle.layout))
    if fit.symmetry is None:
        raise FiberMapError(fit.reason)
    if not fit.symmetry.is_identity:
        log.info("fiducials: the orientation hint was off; the fiber map is %s from it", fit.symmetry.label)
    return reorient_bundle(bundle, fit.symmetry, f"{fit.presses} fiducials")


@dataclass(frozen=True, eq=False)
class RestNoise:
    """What contact-free frames say of the noise (:func:`measure_rest_noise`).

    Attributes
    ----------
    fiber_noise : ndarray, shape (N,), float32
        Each fiber's frame-to-frame noise, gray levels (0 for dead fibers): the camera's noise is additive,
        so relative to a fiber's light it grows as the light falls (:mod:`optitac_edge.core.levels`).
    samples : int
        Frame-to-frame differences each fiber's figure is from (0: fewer than 3 frames, nothing measured).
    noise_rel, noise_gray : float
        The typical (median) live fiber's noise, relative units and gray levels, times
        ``sqrt(1 + 1 / baseline_frames)`` (the averaged baseline's own noise).
    black_level : float
        Median gray level of the pixels that belong to no fiber.
    """

    fiber_noise: np.ndarray
    samples: int
    noise_rel: float
    noise_gray: float
    black_level: float
    #: The frames were farther apart than the gap: the figure is the fibers' drift between snapshots.
    between_snapshots: bool = False

    def summary(self) -> dict[str, float]:
        """For a line a person reads: the typical noise, the black level and the spread of the fibers' noise."""
        live = self.fiber_noise[self.fiber_noise > 0]
        spread = ({"fiber noise gray p90": float(np.percentile(live, 90)), "fiber noise gray max": float(live.max())}
                  if live.size else {})
        return {"noise rel": self.noise_rel, "noise gray": self.noise_gray, "black level": self.black_level, **spread}


def measure_rest_noise(
    rest_frames: Sequence[np.ndarray] | np.ndarray,
    table: FiberTable,
    mean_gray: np.ndarray,
    baseline_frames: int = BASELINE_FRAMES,
    times_ns: np.ndarray | None = None,
    gap_ns: int | None = None,
) -> RestNoise:
    """Noise of each fiber and of the typical fiber, and the black level, from contact-free frames.

    Per-fiber temporal std from frame-to-frame differences (``std(diff) /
    sqrt(2)``: insensitive to slow drift such as LED warm-up), relative to the
    fiber's light above black; the typical fiber's (the median over the live
    fibers: one noisy fiber, or a noisy outer ring of a small array, does not
    set everyone's level: it gets a band of its own,
    :mod:`optitac_edge.core.levels`), scaled by ``sqrt(1 + 1/baseline_frames)``
    for the noise of the averaged baseline. Dead fibers are left out.

    Parameters
    ----------
    rest_frames : sequence of ndarray, uint8
        Contact-free frames in the table's pixel format.
    table : FiberTable
    mean_gray : ndarray, shape (H, W)
        Mean gray image of the rest frames (for the black level).
    times_ns : ndarray, shape (F,), int64, optional
        The frames' capture times, with ``gap_ns``: only differences of frames at most ``gap_ns`` apart count.
        Snapshots seconds to minutes apart differ by each fiber's drift as well; counted as noise, the drift
        was taken for zero-mean noise that a press's values need not lose (:mod:`optitac_edge.core.levels`).
        Fewer than 2 such differences (snapshots): every difference is used, and the result says so
        (``between_snapshots``): what it measured is drift, which the levels subtract (``noise_between_snapshots``).
    """
    from optitac_edge.core.fiber_table import FiberSampler

    labels = table.label_image()
    background = mean_gray[labels == 0]
    black = float(np.median(background)) if background.size else 0.0
    n = table.n_fibers
    close = np.ones(max(len(rest_frames) - 1, 0), dtype=bool)
    if times_ns is not None and gap_ns is not None:
        t = np.asarray(times_ns, dtype=np.int64)
        if t.shape != (len(rest_frames),):
            raise ValueError(f"{t.shape[0] if t.ndim else 0} times for {len(rest_frames)} rest frames")
        close = np.diff(t) <= gap_ns
    between = int(close.sum()) < 2
    if between:  # snapshots: every difference tells drift, not frame-to-frame noise
        close = np.ones_like(close)
    if len(rest_frames) < 3:
        return RestNoise(np.zeros(n, dtype=np.float32), 0, 0.0, 0.0, black)
    sampler = FiberSampler(table)
    buf = np.zeros(n, dtype=np.float32)
    means = np.stack([sampler.means(np.ascontiguousarray(f), buf).astype(np.float64)
                      for f in rest_frames])
    sigma = np.std(np.diff(means, axis=0)[close], axis=0, ddof=1) / math.sqrt(2.0)
    live = ~np.asarray(table.dead, dtype=bool)
    sigma[~live] = 0.0
    level = np.maximum(means.mean(axis=0) - black, 1.0)
    relative = sigma / level
    factor = math.sqrt(1.0 + 1.0 / max(baseline_frames, 1))
    alive = live if live.any() else np.ones(n, dtype=bool)
    return RestNoise(sigma.astype(np.float32), int(close.sum()),
                     factor * float(np.median(relative[alive])), factor * float(np.median(sigma[alive])), black, between)
