"""Build the fiber map (a :class:`~optitac_edge.core.fiber_table.FiberTable`) from rest frames.

Detection (:mod:`optitac_edge.calibration.fiber_detect`) is tried with a short sequence of
parameter sets; each result is registered to the layout
(:mod:`optitac_edge.calibration.fiber_register`) and the one with the most correctly placed
fibers and the fewest stray or merged blobs wins. The search stops early at a
perfect result, or at a clean one (no stray or merged blobs) whose dead fibers
a second parameter set confirms. A map that is not trustworthy is refused with
:class:`~optitac_edge.errors.FiberMapError`.

The rotation hint must be within +-20 degrees of the truth: the hexagonal
array is 60-degree symmetric, so a hint 30 or more degrees off would silently
assign every fiber to a neighbour by a lattice rotation.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from optitac_edge.calibration.fiber_detect import Blobs, DetectParams, detect_fiber_blobs
from optitac_edge.calibration.fiber_register import RegisterParams, Registration, register_blobs
from optitac_edge.core.fiber_table import FiberTable
from optitac_edge.core.frames import PIXEL_FORMATS
from optitac_edge.core.image_transform import ImageTransform
from optitac_edge.core.layout import FiberLayout
from optitac_edge.errors import FiberMapError

log = logging.getLogger(__name__)

_DEFAULT_REGISTER = RegisterParams()

#: Detection parameter sets tried in order.
DEFAULT_DETECT_SEQUENCE: tuple[DetectParams, ...] = (
    DetectParams(),
    DetectParams(normalise="local"),
    DetectParams(normalise="clahe"),
    DetectParams(adaptive_block=1.5),
    DetectParams(marker_frac=0.35, open_frac=0.2),
    DetectParams(normalise="local", marker_frac=0.65, open_frac=0.45),
)


@dataclass(frozen=True)
class MapLimits:
    """Thresholds below which a fiber map is refused.

    Attributes
    ----------
    min_found_fraction : float
        Fraction of layout fibers that must be found.
    max_rms_pitch : float
        Largest acceptable RMS registration residual, pitches.
    max_unmatched_fraction : float
        Largest number of blobs fitting no fiber within the array (a blob farther than ``stray_pitch`` from
        every fiber is stray light, reported and left out), as a fraction of the layout size.
    stray_pitch : float
        A blob farther than this many pitches from every fiber's place is outside the array: stray light
        (a reflection, a lit corner), not a sign of a wrong layout.
    min_pitch_px : float
        Smallest fiber pitch in the image, px.
    max_abs_k1 : float
        Largest plausible radial distortion at the rim (relative stretch).
    dark_ratio : float
        A matched blob dimmer than this fraction of the median blob is a dead fiber.
    """

    min_found_fraction: float = 0.8
    max_rms_pitch: float = 0.15
    max_unmatched_fraction: float = 0.05
    stray_pitch: float = 1.0
    min_pitch_px: float = 4.0
    max_abs_k1: float = 0.3
    dark_ratio: float = 0.35


@dataclass(frozen=True)
class FiberMapReport:
    """Summary of a fiber map build.

    Attributes
    ----------
    n_fibers, n_found : int
        Layout fibers and fibers found.
    dead_fibers : tuple of int
        Layout indices (0..N-1) of fibers not found.
    n_unmatched, n_merged : int
        Blobs fitting no fiber; blobs larger than 1.8x the median (merged faces).
    n_stray : int
        Of the unmatched blobs, those away from the array (farther than ``MapLimits.stray_pitch`` from every
        fiber): stray light, left out.
    residual_rms_px, residual_rms_pitch : float
        RMS distance of found centroids from the fitted transform, px and pitches.
    pitch_px : float
        Fiber pitch in the image, px.
    blob_radius_px : float
        Radius of a disc of the median blob area, px.
    detect_params : DetectParams
        The detection parameters of the kept result.
    attempts : int
        Detection parameter sets tried.
    """

    n_fibers: int
    n_found: int
    dead_fibers: tuple[int, ...]
    n_unmatched: int
    n_merged: int
    residual_rms_px: float
    residual_rms_pitch: float
    pitch_px: float
    blob_radius_px: float
    detect_params: DetectParams
    attempts: int
    n_stray: int = 0

    def summary(self) -> str:
        """One-line human-readable summary."""
        stray = f" ({self.n_stray} away from the array: stray light, left out)" if self.n_stray else ""
        return (
            f"fiber map: {self.n_found}/{self.n_fibers} fibers found, {len(self.dead_fibers)} dead"
            f"{list(self.dead_fibers) if self.dead_fibers else ''}, {self.n_unmatched} unmatched blobs{stray}, "
            f"residual {self.residual_rms_px:.2f} px ({self.residual_rms_pitch:.3f} pitch), "
            f"pitch {self.pitch_px:.1f} px, {self.attempts} detection attempt(s)"
        )


@dataclass(frozen=True, eq=False)
class FiberMapResult:
    """The fiber map: lookup table, layout -> image transform and build report."""

    table: FiberTable
    transform: ImageTransform
    report: FiberMapReport


@dataclass(frozen=True, eq=False)
class _Attempt:
    blobs: Blobs
    reg: Registration
    fiber_blob: np.ndarray  # (N,) blob per fiber, -1 dead (incl. too dark)
    n_merged: int
    n_stray: int  # unmatched blobs away from the array (stray light)

    @property
    def n_found(self) -> int:
        return int(np.count_nonzero(self.fiber_blob >= 0))

    @property
    def n_unmatched(self) -> int:
        return int(self.reg.unmatched.size)

    @property
    def n_within(self) -> int:
        """Unmatched blobs among the fibers (not stray light)."""
        return self.n_unmatched - self.n_stray

    def score(self) -> tuple[int, int, float]:
        return (self.n_found, -(self.n_within + self.n_merged), -self.reg.rms_pitch)


def _stray(blobs: Blobs, reg: Registration, layout: FiberLayout, stray_pitch: float) -> int:
    """Unmatched blobs farther than ``stray_pitch`` pitches from every fiber's place: outside the array."""
    centres = blobs.centroid_px[reg.unmatched].reshape(-1, 2)
    if not centres.size:
        return 0
    places = reg.transform.layout_to_image(layout.xy_mm)
    d = np.hypot(centres[:, None, 0] - places[None, :, 0], centres[:, None, 1] - places[None, :, 1]).min(axis=1)
    return int(np.count_nonzero(d > stray_pitch * reg.pitch_px))


def _mean_image(frames: np.ndarray | Sequence[np.ndarray]) -> np.ndarray:
    """Mean of gray uint8 frames, shape (H, W), float64."""
    if isinstance(frames, np.ndarray) and frames.ndim == 2:
        frames = frames[None]
    arrs = [np.asarray(f) for f in frames]
    if not arrs:
        raise FiberMapError("no rest frames given")
    shape = arrs[0].shape
    if len(shape) != 2 or any(a.shape != shape or a.dtype != np.uint8 for a in arrs):
        raise FiberMapError(
            f"rest frames must be (H, W) uint8 gray images of one size, got {arrs[0].dtype} {shape}"
        )
    acc = np.zeros(shape, dtype=np.float64)
    for a in arrs:
        acc += a
    return acc / len(arrs)


def _check_exposure(mean: np.ndarray) -> None:
    peak = float(np.percentile(mean, 99.9))
    if peak < 30.0:
        raise FiberMapError(
            f"cannot find the fibers: rest frames are dark (99.9th percentile gray {peak:.0f}; is the LED on?)"
        )
    saturated = float(np.mean(mean >= 250.0))
    if saturated > 0.25:
        raise FiberMapError(
            f"cannot find the fibers: rest frames are saturated ({100 * saturated:.0f}% of pixels white; reduce exposure)"
        )
    std = float(mean.std())
    if std < 4.0:
        raise FiberMapError(
            f"cannot find the fibers: rest frames are nearly uniform (gray std {std:.1f}); no fiber array visible"
        )


def _attempt(
    gray: np.ndarray,
    layout: FiberLayout,
    params: DetectParams,
    hint: float,
    mirror: bool,
    reg_params: RegisterParams,
    limits: MapLimits,
) -> _Attempt:
    blobs = detect_fiber_blobs(gray, params)
    n = layout.n_fibers
    if blobs.count > 3 * n:
        raise FiberMapError(
            f"found {blobs.count} bright blobs for {n} fibers (noise or stray light?)"
        )
    reg = register_blobs(blobs.centroid_px, layout, hint, mirror, reg_params)
    fiber_blob = reg.fiber_blob.copy()
    found = fiber_blob >= 0
    if found.any():
        level = blobs.mean_gray[fiber_blob[found]]
        dark = level < limits.dark_ratio * np.median(level)
        fiber_blob[np.flatnonzero(found)[dark]] = -1
    return _Attempt(blobs, reg, fiber_blob, blobs.merged_count(), _stray(blobs, reg, layout, limits.stray_pitch))


def _check_trust(
    a: _Attempt, layout: FiberLayout, shape: tuple[int, int], limits: MapLimits
) -> None:
    n = layout.n_fibers
    if a.n_found < limits.min_found_fraction * n:
        spots = a.blobs.centroid_px
        where = (f" centred at ({spots[:, 0].mean():.0f}, {spots[:, 1].mean():.0f}) px, {a.reg.pitch_px:.1f} px apart"
                 if len(spots) else "")
        raise FiberMapError(
            f"found {a.n_found} of the layout's {n} fibers in the rest frames ({a.blobs.count} bright spots{where}): "
            f"a sensor of {a.blobs.count} fibers needs its own layout (--layout CSV, or a recording made with it); "
            "else check the LED, focus and exposure in the live view")
    t = a.reg.transform
    if a.reg.pitch_px < limits.min_pitch_px:
        raise FiberMapError(f"fiber pitch of {a.reg.pitch_px:.1f} px is too small to resolve")
    if (
        2.0 * layout.radius_mm * t.scale_px_per_mm > 1.5 * max(shape)
        or abs(t.k1) > limits.max_abs_k1
    ):
        raise FiberMapError(
            f"implausible fit (scale {t.scale_px_per_mm:.1f} px/mm, k1 {t.k1:.2f}); wrong layout?"
        )
    if a.reg.rms_pitch > limits.max_rms_pitch:
        raise FiberMapError(
            f"fiber centres fit the layout poorly (residual {a.reg.rms_pitch:.2f} pitch); wrong layout?"
        )
    if a.n_within > max(3, limits.max_unmatched_fraction * n):
        raise FiberMapError(
            f"{a.n_within} bright blobs among the fibers fit no layout fiber (dust on the fiber ends, or a wrong "
            "layout: check the layout CSV's pitch and fiber count against the image in 'optitac-edge view')"
        )


def _disc_pixels(centre: np.ndarray, radius: float, h: int, w: int) -> np.ndarray:
    """Flat indices of a disc at ``centre`` (col, row) inside an (h, w) image; never empty."""
    r = max(radius, 0.5)
    k = int(np.ceil(r))
    dv, du = np.mgrid[-k : k + 1, -k : k + 1]
    inside = du * du + dv * dv <= r * r
    u0, v0 = round(float(centre[0])), round(float(centre[1]))
    u, v = u0 + du[inside], v0 + dv[inside]
    ok = (u >= 0) & (u < w) & (v >= 0) & (v < h)
    if not ok.any():
        return np.array([min(max(v0, 0), h - 1) * w + min(max(u0, 0), w - 1)], dtype=np.int32)
    return (v[ok] * w + u[ok]).astype(np.int32)


def _table(a: _Attempt, layout: FiberLayout, pixel_format: str) -> FiberTable:
    b, t = a.blobs, a.reg.transform
    h, w = b.height, b.width
    predicted = t.layout_to_image(layout.xy_mm)
    dead_radius = max(b.median_radius_px - b.params.inner_erode_px, 1.0)
    groups, centroid = [], predicted.copy()
    for i, j in enumerate(a.fiber_blob):  # per fiber, ~N
        if j >= 0:
            groups.append(b.pixel_index[b.pixel_start[j] : b.pixel_start[j + 1]])
            centroid[i] = b.centroid_px[j]
        else:
            groups.append(_disc_pixels(predicted[i], dead_radius, h, w))
    start = np.zeros(layout.n_fibers + 1, dtype=np.int64)
    np.cumsum([g.size for g in groups], out=start[1:])
    return FiberTable(
        height=h,
        width=w,
        pixel_format=pixel_format,
        pixel_index=np.concatenate(groups).astype(np.int32),
        pixel_start=start,
        centroid_px=centroid,
        dead=a.fiber_blob < 0,
        unmatched_px=b.centroid_px[a.reg.unmatched].reshape(-1, 2),
    )


def build_fiber_map(
    rest_frames_gray: np.ndarray | Sequence[np.ndarray],
    layout: FiberLayout,
    rotation_hint_deg: float = 0.0,
    mirror: bool = False,
    pixel_format: str = "gray",
    *,
    detect_sequence: Sequence[DetectParams] = DEFAULT_DETECT_SEQUENCE,
    register_params: RegisterParams = _DEFAULT_REGISTER,
    limits: MapLimits = MapLimits(),
) -> FiberMapResult:
    """Find every layout fiber's pixels in contact-free rest frames.

    Parameters
    ----------
    rest_frames_gray : ndarray, shape (K, H, W) or (H, W), uint8, or a sequence of (H, W) uint8
        Grayscale rest frames (luminance plane, see :func:`optitac_edge.core.frames.to_gray`);
        their mean is used.
    layout : FiberLayout
        The sensor's CAD layout.
    rotation_hint_deg : float
        The array appears rotated counter-clockwise by about this angle, degrees;
        must be within +-20 degrees of the truth (see module docstring).
    mirror : bool
        The image is mirrored (layout x negated before rotation).
    pixel_format : str
        Pixel format of the frames the table will be applied to (recorded in it).
    detect_sequence : sequence of DetectParams
        Detection parameter sets to try, in order.
    register_params : RegisterParams
        Matching parameters.
    limits : MapLimits
        When to refuse the map.

    Returns
    -------
    FiberMapResult
        Table (pixels, centroids, dead mask in layout order), transform, report.

    Raises
    ------
    FiberMapError
        If the frames are dark, saturated or uniform, or the best map found
        is not trustworthy (too few fibers, poor fit, implausible scale, stray blobs).
    """
    if pixel_format not in PIXEL_FORMATS:
        raise FiberMapError(f"unknown pixel format {pixel_format!r}")
    mean = _mean_image(rest_frames_gray)
    _check_exposure(mean)
    gray = np.clip(np.rint(mean), 0, 255).astype(np.uint8)
    best: _Attempt | None = None
    failure: FiberMapError | None = None
    tried = 0
    for params in detect_sequence:
        tried += 1
        try:
            a = _attempt(gray, layout, params, rotation_hint_deg, mirror, register_params, limits)
        except FiberMapError as exc:
            failure = failure or exc
            continue
        clean = a.n_within == 0 and a.n_merged == 0
        confirmed = (
            best is not None
            and clean
            and best.n_within == 0
            and best.n_merged == 0
            and np.array_equal(best.fiber_blob < 0, a.fiber_blob < 0)
        )
        if best is None or a.score() > best.score():
            best = a
        if (clean and a.n_found == layout.n_fibers) or confirmed:
            break
    if best is None:
        assert failure is not None
        raise failure
    _check_trust(best, layout, gray.shape, limits)
    reg = best.reg
    report = FiberMapReport(
        n_fibers=layout.n_fibers,
        n_found=best.n_found,
        dead_fibers=tuple(int(i) for i in np.flatnonzero(best.fiber_blob < 0)),
        n_unmatched=best.n_unmatched,
        n_merged=best.n_merged,
        residual_rms_px=reg.rms_px,
        residual_rms_pitch=reg.rms_pitch,
        pitch_px=reg.pitch_px,
        blob_radius_px=best.blobs.median_radius_px,
        detect_params=best.blobs.params,
        attempts=tried,
        n_stray=best.n_stray,
    )
    log.info(report.summary())
    return FiberMapResult(
        table=_table(best, layout, pixel_format), transform=reg.transform, report=report
    )
