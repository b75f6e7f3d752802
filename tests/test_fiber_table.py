import numpy as np
import pytest
from scipy import ndimage

from optitac_edge.core.fiber_table import FiberSampler, FiberTable
from optitac_edge.core.frames import to_gray


def _table(pixel_format: str, h: int = 30, w: int = 40, n: int = 9) -> FiberTable:
    rng = np.random.default_rng(0)
    pixels = rng.choice(h * w, size=n * 7, replace=False).astype(np.int32)
    return FiberTable(height=h, width=w, pixel_format=pixel_format, pixel_index=pixels,
                      pixel_start=np.arange(0, n * 7 + 1, 7), centroid_px=np.zeros((n, 2)),
                      dead=np.zeros(n, bool), unmatched_px=np.zeros((0, 2)))


@pytest.mark.parametrize("pixel_format", ["gray", "yuv420", "rgb"])
def test_means_equal_labelled_means_of_the_gray_image(pixel_format):
    table = _table(pixel_format)
    rng = np.random.default_rng(1)
    shape = {"gray": (30, 40), "yuv420": (45, 40), "rgb": (30, 40, 3)}[pixel_format]
    frame = rng.integers(0, 256, shape, dtype=np.uint8)
    out = FiberSampler(table).means(frame, np.empty(table.n_fibers, np.float32))
    # RGB: exactly cv2.cvtColor's rounded gray of the whole frame (as calibration and the reference)
    gray = to_gray(frame, pixel_format).astype(np.float64)
    labels = table.label_image()
    expected = ndimage.mean(gray, labels, np.arange(1, table.n_fibers + 1))
    np.testing.assert_allclose(out, expected, rtol=1e-5)


def test_label_image_marks_each_fiber_pixel():
    table = _table("gray")
    labels = table.label_image().ravel()
    for i in range(table.n_fibers):
        assert np.all(labels[table.pixel_index[table.pixel_start[i]:table.pixel_start[i + 1]]] == i + 1)
    assert np.count_nonzero(labels) == table.pixel_index.size


def test_a_table_needs_pixels_inside_the_image():
    with pytest.raises(ValueError):
        FiberTable(height=2, width=2, pixel_format="gray", pixel_index=np.array([0, 9], np.int32),
                   pixel_start=np.array([0, 1, 2]), centroid_px=np.zeros((2, 2)), dead=np.zeros(2, bool),
                   unmatched_px=np.zeros((0, 2)))


@pytest.mark.parametrize("pixels", [257, 258, 600])
def test_means_are_exact_for_large_fibers_on_a_saturated_frame(pixels):
    """255 * 257 = 65535 is the most a 16-bit sum holds: larger fibers need wider sums."""
    h, w = 40, 40
    sizes = np.array([pixels, 3, pixels - 1])
    starts = np.concatenate([[0], np.cumsum(sizes)])
    table = FiberTable(height=h, width=w, pixel_format="gray",
                       pixel_index=np.random.default_rng(2).permutation(h * w)[:starts[-1]].astype(np.int32),
                       pixel_start=starts, centroid_px=np.zeros((3, 2)), dead=np.zeros(3, bool),
                       unmatched_px=np.zeros((0, 2)))
    sampler = FiberSampler(table)
    out = np.empty(3, np.float32)
    np.testing.assert_array_equal(sampler.means(np.full((h, w), 255, np.uint8), out), [255.0] * 3)
    frame = np.random.default_rng(3).integers(200, 256, (h, w), dtype=np.uint8)
    expected = ndimage.mean(frame.astype(np.float64), table.label_image(), np.arange(1, 4))
    np.testing.assert_allclose(sampler.means(frame, out), expected, rtol=1e-6)
