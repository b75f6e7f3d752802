"""Find the fiber end faces in a rest image: Otsu, morphological opening, watershed.

The method of the OptiTac paper: binarize the (mean) rest image with Otsu's
threshold, remove specks with an opening (erosion then dilation) whose kernel
is scaled to the blob size, then split touching end faces with a marker-based
watershed (markers: the core of each component, where the distance transform
exceeds a fraction of the component's maximum). Every label is one blob, ideally
one fiber end face; which blob is which layout fiber is decided by
:mod:`optitac_edge.calibration.fiber_register`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

Normalisation = Literal["none", "clahe", "local"]


@dataclass(frozen=True)
class DetectParams:
    """Parameters of :func:`detect_fiber_blobs`.

    Attributes
    ----------
    normalise : {"none", "clahe", "local"}
        Contrast normalisation before Otsu: none (global Otsu), CLAHE, or
        division by a local maximum (evens out LED vignetting).
    blur_sigma_px : float
        Gaussian pre-blur, px (0 disables).
    open_frac : float
        Opening kernel diameter as a fraction of the estimated blob diameter.
    marker_frac : float
        Watershed markers: pixels whose distance to the background is at least
        this fraction of their component's maximum distance.
    adaptive_block : float
        If > 0, a pixel must also exceed the mean of a box of this many blob
        diameters around it (splits end faces merged by blur or bloom).
    min_area_frac : float
        Blobs smaller than this fraction of the median blob area are dropped.
    inner_erode_px : int
        Each blob's returned pixels are its label eroded by this many pixels
        (the inner part of the end face); a blob that would vanish keeps all.
    """

    normalise: Normalisation = "none"
    blur_sigma_px: float = 1.0
    open_frac: float = 0.3
    marker_frac: float = 0.5
    adaptive_block: float = 0.0
    min_area_frac: float = 0.25
    inner_erode_px: int = 1


@dataclass(frozen=True, eq=False)
class Blobs:
    """Detected blobs; pixels grouped per blob like :class:`~optitac_edge.core.fiber_table.FiberTable`.

    Attributes
    ----------
    height, width : int
        Image size, px.
    centroid_px : ndarray, shape (K, 2), float64
        Blob centroids (col, row), px (unweighted mean of the label's pixels).
    area_px : ndarray, shape (K,), int64
        Pixels in each watershed label.
    mean_gray : ndarray, shape (K,), float64
        Mean gray level (0-255, of the input image) of each blob's inner pixels.
    pixel_index : ndarray, shape (P,), int32
        Flat indices (``row * width + col``) of the inner pixels, grouped by blob.
    pixel_start : ndarray, shape (K + 1,), int64
        Blob ``k`` owns ``pixel_index[pixel_start[k]:pixel_start[k + 1]]``.
    params : DetectParams
        The parameters used.
    """

    height: int
    width: int
    centroid_px: np.ndarray
    area_px: np.ndarray
    mean_gray: np.ndarray
    pixel_index: np.ndarray
    pixel_start: np.ndarray
    params: DetectParams

    @property
    def count(self) -> int:
        return int(self.centroid_px.shape[0])

    @property
    def median_radius_px(self) -> float:
        """Radius of a disc of the median blob area, px (0 if there are no blobs)."""
        return float(np.sqrt(np.median(self.area_px) / np.pi)) if self.count else 0.0

    def merged_count(self, factor: float = 1.8) -> int:
        """Blobs larger than ``factor`` times the median area (likely merged end faces)."""
        if not self.count:
            return 0
        return int(np.count_nonzero(self.area_px > factor * np.median(self.area_px)))


def _odd(n: float) -> int:
    k = max(1, round(float(n)))
    return k if k % 2 else k + 1


def _disc(diameter: float) -> np.ndarray:
    d = _odd(diameter)
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d))


def _otsu(img: np.ndarray) -> np.ndarray:
    _, binary = cv2.threshold(img, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    return binary


def estimate_pitch_px(img: np.ndarray) -> float:
    """Dominant spacing of a periodic pattern in ``img`` (H, W), px; 0 if none.

    The first peak of the radially averaged autocorrelation (via FFT) of the
    high-passed image.
    """
    f = img.astype(np.float32)
    # High-pass: the array (~17 pitches across) fits the image, so the pitch is
    # below min(H, W) / 16; remove the array's overall shape and vignetting.
    f -= cv2.GaussianBlur(f, (0, 0), min(img.shape) / 16.0)
    spec = np.fft.rfft2(f)
    ac = np.fft.fftshift(np.fft.irfft2(spec.real**2 + spec.imag**2, s=f.shape))
    h, w = ac.shape
    rr = np.hypot(*np.meshgrid(np.arange(w) - w // 2, np.arange(h) - h // 2)).astype(np.int64)
    n_r = min(h, w) // 4
    sel = rr < n_r
    prof = np.bincount(rr[sel], weights=ac[sel], minlength=n_r) / np.maximum(
        np.bincount(rr[sel], minlength=n_r), 1
    )
    d = np.diff(prof)
    rising = np.flatnonzero((d[:-1] > 0) & (d[1:] <= 0)) + 1  # local maxima of the profile
    rising = rising[rising >= 3]
    return float(rising[0]) if rising.size else 0.0


def estimate_blob_radius(img: np.ndarray) -> float:
    """Typical end-face radius, px, from a plain Otsu binarization of ``img`` (H, W) uint8.

    The median area of the components not much smaller than the 90th-percentile
    area, so specks and a few merged blobs do not matter. If fewer than 7 such
    components exist (end faces merged into one region), a third of the pattern
    pitch (:func:`estimate_pitch_px`) instead. Returns 0 if nothing is found.
    """
    n, _, stats, _ = cv2.connectedComponentsWithStats(_otsu(img), connectivity=8)
    areas = stats[1:n, cv2.CC_STAT_AREA].astype(np.float64)
    if areas.size == 0:
        return 0.0
    ref = np.percentile(areas, 90)
    big = areas[areas >= 0.2 * ref]
    if big.size < 7:
        return estimate_pitch_px(img) / 3.0
    return float(np.sqrt(np.median(big) / np.pi))


def _normalised(img: np.ndarray, how: Normalisation, radius: float) -> np.ndarray:
    if how == "none":
        return img
    if how == "clahe":
        tiles = max(2, round(float(min(img.shape) / max(8.0 * radius, 8.0))))
        return cv2.createCLAHE(clipLimit=3.0, tileGridSize=(tiles, tiles)).apply(img)
    if how == "local":
        # Divide by a smoothed local maximum over ~3 pitches (evens out vignetting),
        # computed on a downsampled image; floored so the dark surround stays dark.
        f = max(1.0, radius / 2.0)
        small = cv2.resize(img, None, fx=1.0 / f, fy=1.0 / f, interpolation=cv2.INTER_AREA)
        peak = cv2.dilate(small, _disc(10.0 * radius / f)).astype(np.float32)
        peak = np.asarray(cv2.blur(peak, (_odd(10.0 * radius / f),) * 2))
        peak = np.asarray(cv2.resize(peak, (img.shape[1], img.shape[0]), interpolation=cv2.INTER_LINEAR))
        floor = max(8.0, 0.25 * float(peak.max()))
        out = img.astype(np.float32) * (255.0 / np.maximum(peak, floor))
        return np.clip(out, 0, 255).astype(np.uint8)
    raise ValueError(f"unknown normalisation {how!r}")


def _watershed(img: np.ndarray, binary: np.ndarray, marker_frac: float) -> np.ndarray:
    """Label image (H, W) int32: 0 background, 1..M blobs (watershed ridges -> 0)."""
    n_cc, cc_mat = cv2.connectedComponents(binary, connectivity=8)
    cc = np.asarray(cc_mat, dtype=np.int32)
    dist = np.asarray(cv2.distanceTransform(binary, cv2.DIST_L2, 5))
    cc_max = np.zeros(n_cc, dtype=np.float32)
    fg = cc > 0
    np.maximum.at(cc_max, cc[fg], dist[fg])
    sure_fg = (dist >= marker_frac * cc_max[cc]) & (cc > 0)
    _, markers = cv2.connectedComponents(sure_fg.astype(np.uint8), connectivity=8)
    markers = markers + 1  # 1: sure background, 2..: blob cores, 0: to be flooded
    markers[(binary > 0) & ~sure_fg] = 0
    cv2.watershed(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR), markers)
    labels = markers - 1
    labels[(labels < 1) | (binary == 0)] = 0
    return labels


def _group(labels_flat: np.ndarray, keep: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel indices of labels 1..n where ``keep``, grouped by label; and starts."""
    idx = np.flatnonzero(keep)
    lab = labels_flat[idx]
    order = np.argsort(lab, kind="stable")
    counts = np.bincount(lab, minlength=n + 1)[1:]
    start = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(counts, out=start[1:])
    return idx[order].astype(np.int32), start


def detect_fiber_blobs(gray: np.ndarray, params: DetectParams = DetectParams()) -> Blobs:
    """Detect bright fiber end faces in a rest image.

    Parameters
    ----------
    gray : ndarray, shape (H, W), uint8
        Mean of the rest frames, grayscale.
    params : DetectParams
        Detection parameters.

    Returns
    -------
    Blobs
        One blob per watershed label (specks below ``min_area_frac`` of the
        median area removed), in no particular order.
    """
    if gray.ndim != 2 or gray.dtype != np.uint8:
        raise ValueError("gray must be a (H, W) uint8 image")
    h, w = gray.shape
    img = gray
    if params.blur_sigma_px > 0:
        img = cv2.GaussianBlur(gray, (0, 0), params.blur_sigma_px)
    radius = estimate_blob_radius(img)
    img = _normalised(img, params.normalise, radius)
    binary = _otsu(img)
    if params.adaptive_block > 0 and radius > 0:
        box = _odd(params.adaptive_block * 2.0 * radius)
        local = cv2.blur(img.astype(np.float32), (box, box))
        binary[img.astype(np.float32) <= local] = 0
    if radius > 0 and params.open_frac > 0:
        binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, _disc(params.open_frac * 2.0 * radius))
    labels = _watershed(img, binary, params.marker_frac)
    n = int(labels.max())
    flat = labels.reshape(-1)
    fg_idx = np.flatnonzero(flat)
    fg_lab = flat[fg_idx]
    area = np.bincount(fg_lab, minlength=n + 1)[1:].astype(np.int64)
    rows, cols = np.divmod(fg_idx, w)
    with np.errstate(invalid="ignore", divide="ignore"):
        cu = np.bincount(fg_lab, weights=cols, minlength=n + 1)[1:] / area
        cv = np.bincount(fg_lab, weights=rows, minlength=n + 1)[1:] / area
    keep_lab = area > 0
    if keep_lab.any():
        keep_lab &= area >= params.min_area_frac * np.median(area[keep_lab])
    # Renumber kept labels 1..M.
    new_id = np.zeros(n + 1, dtype=np.int32)
    new_id[1:][keep_lab] = np.arange(1, int(keep_lab.sum()) + 1, dtype=np.int32)
    labels = new_id[labels]
    m = int(keep_lab.sum())
    flat = labels.reshape(-1)
    inner = flat > 0
    if params.inner_erode_px > 0 and m:
        k = _disc(2 * params.inner_erode_px + 1)
        lf = labels.astype(np.float32)
        same = (cv2.erode(lf, k) == lf) & (cv2.dilate(lf, k) == lf)
        inner_try = inner & same.reshape(-1)
        has_inner = np.bincount(flat[inner_try], minlength=m + 1)[1:] > 0
        inner = inner_try | (inner & ~np.concatenate(([True], has_inner))[flat])
    pixel_index, pixel_start = _group(flat, inner, m)
    sums = (
        np.add.reduceat(gray.reshape(-1)[pixel_index].astype(np.float64), pixel_start[:-1])
        if m
        else np.zeros(0)
    )
    return Blobs(
        height=h,
        width=w,
        centroid_px=np.stack([cu[keep_lab], cv[keep_lab]], axis=1),
        area_px=area[keep_lab],
        mean_gray=sums / np.diff(pixel_start) if m else np.zeros(0),
        pixel_index=pixel_index,
        pixel_start=pixel_start,
        params=params,
    )
