"""Several sensors in one camera frame: regions, bundles placed in the frame, no cross-talk (issue 16)."""

from __future__ import annotations

import numpy as np
import pytest

from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.calibration.region import Region, bundle_region, place_bundle, place_fiber_table
from optitac_edge.core.fiber_table import FiberTable
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.io.bundle_file import load_bundle, save_bundle
from optitac_edge.sim.patches import PatchFrames, crop
from optitac_edge.sim.skin import Indenter


def test_a_placed_fiber_table_labels_the_same_pixels_at_the_region_offset():
    table = FiberTable(height=4, width=5, pixel_format="gray", pixel_index=np.array([0, 6, 7, 19], dtype=np.int32),
                       pixel_start=np.array([0, 1, 3, 4]), centroid_px=np.array([[0.0, 0.0], [1.5, 1.0], [4.0, 3.0]]),
                       dead=np.zeros(3, dtype=bool), unmatched_px=np.zeros((0, 2)))
    placed = place_fiber_table(table, Region(10, 2, 5, 4), 20, 8)
    big = placed.label_image()
    assert np.array_equal(big[2:6, 10:15], table.label_image()) and big.sum() == table.label_image().sum()
    assert np.array_equal(placed.centroid_px, table.centroid_px + [10, 2])
    with pytest.raises(ValueError, match="leaves the 14x8 frame"):
        place_fiber_table(table, Region(10, 2, 5, 4), 14, 8)
    with pytest.raises(ValueError, match="the region is 6x4"):
        place_fiber_table(table, Region(0, 0, 6, 4), 20, 8)


@pytest.mark.parametrize("bad", [(-1, 0, 4, 4), (0, 0, 0, 4), (0.5, 0, 4, 4)])
def test_a_bad_region_is_refused(bad):
    with pytest.raises((TypeError, ValueError), match="region"):
        Region(*bad)
    assert Region(0, 0, 4, 4).overlaps(Region(3, 3, 4, 4)) and not Region(0, 0, 4, 4).overlaps(Region(4, 0, 4, 4))


@pytest.fixture(scope="module")
def two_patches(tmp_path_factory):
    """Two hexagonal patches side by side on one 960x400 camera, each calibrated on its crop and placed."""
    regions = [Region(0, 20, 440, 360), Region(500, 30, 440, 360)]
    cam = PatchFrames(regions, 960, 400, seed=4)
    rest = np.stack([cam.frame() for _ in range(10)])
    bundles = []
    tmp = tmp_path_factory.mktemp("patches")
    for k, r in enumerate(regions):
        placed = place_bundle(calibrate_fibers(crop(rest, r), "gray"), r, 960, 400)
        save_bundle(placed, tmp / f"patch{k}.npz")
        bundles.append(load_bundle(tmp / f"patch{k}.npz"))  # the region survives a file
    return cam, rest, bundles


def test_each_patch_sees_its_own_presses_and_none_of_the_others(two_patches):
    cam, rest, bundles = two_patches
    assert [bundle_region(b) for b in bundles] == cam.regions
    pipes = [Pipeline(b) for b in bundles]
    t = 0
    for f in rest:
        for p in pipes:
            p.process_recorded(f, t)
        t += 4_166_667
    rng = np.random.default_rng(8)
    counts = np.zeros((2, 2), dtype=int)  # [pressed patch, patch reporting] -> frames with a contact
    errors = []
    for i in range(40):
        k = i % 2
        press = Indenter("circle", float(rng.uniform(-5, 5)), float(rng.uniform(-5, 5)), 0.0, 5.0, 3.0)
        frame = cam.frame([(press,) if j == k else () for j in range(2)])
        for j, p in enumerate(pipes):
            est = p.process_recorded(frame, t).primary
            counts[k, j] += est.contact
            if j == k and est.contact:
                errors.append(np.hypot(est.x_mm - press.x_mm, est.y_mm - press.y_mm))
        t += 4_166_667
        for p in pipes:  # a contact-free frame between presses
            p.process_recorded(cam.frame(), t)
        t += 4_166_667
    assert counts[0, 0] == 20 and counts[1, 1] == 20  # every press found on its patch
    assert counts[0, 1] == 0 and counts[1, 0] == 0  # no cross-talk
    assert np.sqrt(np.mean(np.square(errors))) < 0.5  # raw centroids (no error map), mm


def test_a_bundle_is_refused_on_a_frame_of_another_size(two_patches):
    from optitac_edge.errors import FrameMismatchError

    _, rest, bundles = two_patches
    with pytest.raises(FrameMismatchError):
        bundles[0].fibers.check_frame(np.ascontiguousarray(rest[0][:, :900]), "gray")
    with pytest.raises(ValueError, match="already placed"):
        place_bundle(bundles[0], Region(0, 0, 440, 360), 960, 400)
