"""Blob detection: Otsu + opening + watershed on synthetic rest images."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from test_fiber_synth import Synth, render, true_centres

from optitac_edge.calibration.fiber_detect import (
    DetectParams,
    detect_fiber_blobs,
    estimate_blob_radius,
    estimate_pitch_px,
)


def _mean_gray(s: Synth, n: int = 2) -> np.ndarray:
    return np.rint(render(s, n_frames=n).mean(axis=0)).astype(np.uint8)


@pytest.mark.parametrize(
    "params",
    [
        DetectParams(),
        DetectParams(normalise="local"),
        DetectParams(normalise="clahe"),
        DetectParams(adaptive_block=1.5),
    ],
    ids=["otsu", "local", "clahe", "adaptive"],
)
def test_one_blob_per_fiber_near_its_centre(params: DetectParams) -> None:
    s = Synth(rotation_deg=17.0)
    blobs = detect_fiber_blobs(_mean_gray(s), params)
    centres, scale = true_centres(s)
    d, idx = cKDTree(centres).query(blobs.centroid_px)
    assert blobs.count == 217
    assert len(set(idx.tolist())) == 217
    assert d.max() < 0.1 * 1.5 * scale  # well within 0.1 pitch
    assert blobs.merged_count() == 0


def test_blob_pixels_are_grouped_and_inside_their_face() -> None:
    s = Synth()
    gray = _mean_gray(s)
    blobs = detect_fiber_blobs(gray)
    counts = np.diff(blobs.pixel_start)
    assert blobs.pixel_index.dtype == np.int32 and blobs.pixel_start.dtype == np.int64
    assert np.all(counts >= 1) and blobs.pixel_start[-1] == blobs.pixel_index.size
    assert np.unique(blobs.pixel_index).size == blobs.pixel_index.size  # no pixel in two blobs
    rows, cols = np.divmod(blobs.pixel_index.astype(np.int64), blobs.width)
    owner = np.repeat(np.arange(blobs.count), counts)
    dist = np.hypot(cols - blobs.centroid_px[owner, 0], rows - blobs.centroid_px[owner, 1])
    assert dist.max() <= blobs.median_radius_px + 1.0
    assert np.all(counts < blobs.area_px)  # inner part: eroded
    assert np.all(blobs.mean_gray > 60)


def test_touching_faces_are_split() -> None:
    # Faces 1.45 mm at 1.5 mm pitch, blurred: they merge under a global threshold.
    s = Synth(face_mm=1.45, blur_px=2.0, vignetting=0.1)
    gray = _mean_gray(s)
    blobs = detect_fiber_blobs(gray, DetectParams(adaptive_block=1.5))
    centres, scale = true_centres(s)
    d, idx = cKDTree(centres).query(blobs.centroid_px)
    assert blobs.count == 217 and len(set(idx.tolist())) == 217
    assert d.max() < 0.15 * 1.5 * scale


def test_size_estimates() -> None:
    s = Synth()
    gray = _mean_gray(s)
    _, scale = true_centres(s)
    assert estimate_blob_radius(gray) == pytest.approx(0.5 * scale, rel=0.25)
    assert estimate_pitch_px(gray) == pytest.approx(1.5 * scale, rel=0.1)
    assert estimate_blob_radius(np.zeros((50, 60), np.uint8)) == 0.0


def test_rejects_non_uint8() -> None:
    with pytest.raises(ValueError):
        detect_fiber_blobs(np.zeros((10, 10), np.float32))
