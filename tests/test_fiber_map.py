"""Fiber map acceptance: the simulator's rest frames -> every fiber found and assigned right.

Uses :mod:`optitac_edge.sim` (its own Brown k1, k2 + tangential distortion); the
failure-mode tests need no simulator.
"""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
from test_fiber_synth import Synth, render, true_centres

from optitac_edge.calibration.fiber_map import FiberMapResult, build_fiber_map
from optitac_edge.core.fiber_table import FiberSampler
from optitac_edge.core.frames import to_gray
from optitac_edge.core.layout import hex_layout
from optitac_edge.errors import FiberMapError
from optitac_edge.sim.optics import CameraOptics
from optitac_edge.sim.sensor import SimulatedSensor

LAYOUT = hex_layout()
DARK = (0, 37, 108, 150, 216)  # rim corners 0 and 216, the central fiber 108


def _sim_frames(n: int = 3, seed: int = 0, **optics: object) -> tuple[np.ndarray, SimulatedSensor]:
    sensor = SimulatedSensor(optics=CameraOptics(**optics), seed=seed)
    frames = [sensor.frame() for _ in range(n)]
    if frames[0].ndim == 3:
        frames = [to_gray(f, "rgb") for f in frames]
    return np.stack(frames), sensor


def _check_assignment(
    res: FiberMapResult, truth_px: np.ndarray, dead: tuple[int, ...] = ()
) -> None:
    assert res.report.dead_fibers == dead
    assert res.report.n_found == 217 - len(dead) and res.report.n_unmatched == 0
    alive = ~res.table.dead
    err = np.linalg.norm(res.table.centroid_px - truth_px, axis=1) / res.report.pitch_px
    assert np.all(err[alive] < 0.3), f"worst fiber {int(np.argmax(np.where(alive, err, 0)))}"
    # Dead fibers: predicted centre still lands on the right fiber.
    assert np.all(err[~alive] < 0.3)
    assert res.report.residual_rms_pitch < 0.1


def _sweep(width: int, height: int, step: int) -> list[tuple[int, int, float, bool]]:
    cases = []
    for k, rot in enumerate(range(0, 360, step)):
        for mirror in (False, True):
            cases.append((width, height, float(rot), mirror))
    return cases


SWEEP = _sweep(640, 480, 15) + _sweep(1280, 720, 90) + _sweep(1920, 1080, 120)


@pytest.mark.parametrize("width,height,rot,mirror", SWEEP)
def test_rotation_sweep_all_fibers_assigned(
    width: int, height: int, rot: float, mirror: bool
) -> None:
    frames, sensor = _sim_frames(
        width=width, height=height, rotation_deg=rot, mirror=mirror, seed=int(rot)
    )
    hint_error = 20.0 if (int(rot) // 15 + mirror) % 2 else -20.0
    res = build_fiber_map(frames, LAYOUT, rotation_hint_deg=rot + hint_error, mirror=mirror)
    _check_assignment(res, sensor.fiber_centres_px)
    d = (res.transform.rotation_deg - rot + 180.0) % 360.0 - 180.0
    assert abs(d) < 1.0 and res.transform.mirror == mirror


@pytest.mark.parametrize(
    "width,height,rot,mirror",
    [(640, 480, 0.0, False), (640, 480, 215.0, True), (1920, 1080, 100.0, False)],
)
def test_dark_fibers_reported_dead(width: int, height: int, rot: float, mirror: bool) -> None:
    frames, sensor = _sim_frames(
        width=width, height=height, rotation_deg=rot, mirror=mirror, dark_fibers=DARK
    )
    res = build_fiber_map(frames, LAYOUT, rotation_hint_deg=rot - 12.0, mirror=mirror)
    _check_assignment(res, sensor.fiber_centres_px, DARK)
    assert np.array_equal(np.flatnonzero(res.table.dead), DARK)


def test_table_samples_fiber_brightness() -> None:
    frames, sensor = _sim_frames(rotation_deg=30.0, dark_fibers=(5,), rgb=True)
    rgb_frame = sensor.frame()
    res = build_fiber_map(list(frames), LAYOUT, rotation_hint_deg=25.0, pixel_format="rgb")
    table = res.table
    assert (table.height, table.width, table.pixel_format) == (480, 640, "rgb")
    assert table.pixel_index.dtype == np.int32 and table.pixel_start.shape == (218,)
    assert table.unmatched_px.shape == (0, 2)
    labels = table.label_image()
    assert np.unique(labels).size == 218  # background + every fiber owns pixels
    table.check_frame(rgb_frame, "rgb")
    means = FiberSampler(table).means(rgb_frame, np.empty(217, np.float32))
    alive = ~table.dead
    assert np.corrcoef(means[alive], sensor.rest_peak[alive])[0, 1] > 0.9
    assert means[5] < 0.3 * np.median(means[alive])  # dead fiber's disc sits on dark pixels


def test_nearly_touching_faces_are_split() -> None:
    # 1.45 mm faces at 1.5 mm pitch, blurred: Otsu merges them into one region.
    frames, sensor = _sim_frames(rotation_deg=23.0, fiber_diameter_mm=1.45, blur_sigma_px=2.0)
    res = build_fiber_map(frames, LAYOUT, rotation_hint_deg=10.0)
    _check_assignment(res, sensor.fiber_centres_px)
    assert res.report.n_merged == 0


@pytest.mark.parametrize("width,height", [(640, 480), (1280, 720), (1920, 1080)])
def test_build_time(width: int, height: int) -> None:
    frames, _ = _sim_frames(n=5, width=width, height=height, rotation_deg=45.0, dark_fibers=DARK)
    t0 = time.perf_counter()
    build_fiber_map(frames, LAYOUT, rotation_hint_deg=45.0)
    assert time.perf_counter() - t0 < 5.0


def test_synthetic_renderer_with_dead_fibers_and_logging(caplog: pytest.LogCaptureFixture) -> None:
    s = Synth(rotation_deg=123.0, mirror=True, dark_fibers=(3, 108, 200))
    with caplog.at_level(logging.INFO, logger="optitac_edge.calibration.fiber_map"):
        res = build_fiber_map(render(s, n_frames=3), LAYOUT, rotation_hint_deg=140.0, mirror=True)
    _check_assignment(res, true_centres(s)[0], (3, 108, 200))
    assert len(caplog.records) == 1 and "214/217 fibers found" in caplog.records[0].getMessage()


_RNG = np.random.default_rng(7)


@pytest.mark.parametrize(
    "frames,message",
    [
        (np.zeros((3, 480, 640), np.uint8), "dark"),
        (np.full((3, 480, 640), 255, np.uint8), "saturated"),
        (np.full((3, 480, 640), 128, np.uint8), "uniform"),
        (_RNG.integers(0, 256, (3, 480, 640), dtype=np.uint8), "blobs|fibers"),
        (_RNG.integers(0, 256, (1, 480, 640), dtype=np.uint8), "blobs|fibers"),
        (np.clip(_RNG.normal(40, 25, (4, 480, 640)), 0, 255).astype(np.uint8), "blobs|fibers"),
    ],
    ids=["black", "saturated", "uniform", "noise3", "noise1", "gauss-noise"],
)
def test_untrustworthy_frames_refused(frames: np.ndarray, message: str) -> None:
    with pytest.raises(FiberMapError, match=message):
        build_fiber_map(frames, LAYOUT)


def test_too_few_fibers_refused() -> None:
    s = Synth(rotation_deg=5.0)
    frames = render(s, n_frames=2)
    frames[:, :, : frames.shape[2] // 2] = 12  # left half of the array hidden
    with pytest.raises(FiberMapError, match=r"found \d+ of the layout's 217 fibers in the rest frames \(\d+ bright spots"):
        build_fiber_map(frames, LAYOUT, rotation_hint_deg=0.0)


def test_wrong_layout_refused() -> None:
    frames = render(Synth(), n_frames=2)
    with pytest.raises(FiberMapError, match="fibers|layout"):
        build_fiber_map(frames, hex_layout(rings=11), rotation_hint_deg=0.0)


def test_bad_input_refused() -> None:
    with pytest.raises(FiberMapError, match="uint8"):
        build_fiber_map(np.zeros((2, 48, 64), np.float32), LAYOUT)
    with pytest.raises(FiberMapError, match="no rest frames"):
        build_fiber_map([], LAYOUT)
    with pytest.raises(FiberMapError, match="pixel format"):
        build_fiber_map(render(Synth(), 1), LAYOUT, pixel_format="bgr")


def _with_corner_blobs(frames: np.ndarray, gray: float, where: list[tuple[int, int]]) -> np.ndarray:
    import cv2

    out = []
    for f in frames:
        g = f.astype(np.float32)
        for c, r in where:
            cv2.circle(g, (c, r), 8, gray, -1)
        out.append(np.clip(np.rint(g), 0, 255).astype(np.uint8))
    return np.stack(out)


def test_stray_blobs_away_from_the_array_are_reported_and_left_out() -> None:
    """A 61-fiber, 4 mm-pitch array with four lit blobs in the image corners (a real sensor's rest frames
    had them): the map was refused ("4 bright blobs fit no layout fiber"); now every fiber is found, the
    four are reported as stray and left out of the table's fibers."""
    layout = hex_layout(4, 4.0)
    sensor = SimulatedSensor(layout=layout, optics=CameraOptics(background_gray=18, led_peak_gray=60,
                                                                fiber_diameter_mm=1.3))
    corners = [(20, 20), (620, 25), (25, 460), (615, 455)]
    frames = _with_corner_blobs(np.stack([sensor.frame() for _ in range(4)]), 50.0, corners)
    result = build_fiber_map(frames, layout)
    assert result.report.n_found == 61 and result.report.n_stray == 4 and result.report.n_unmatched == 4
    np.testing.assert_allclose(result.table.centroid_px, sensor.fiber_centres_px, atol=0.5)
    assert "4 away from the array" in result.report.summary()


def test_unmatched_blobs_among_the_fibers_are_still_refused() -> None:
    """Blobs between the fibers are no stray light: many of them mean a wrong layout, and the line says what
    to check."""
    layout = hex_layout(4, 4.0)
    sensor = SimulatedSensor(layout=layout, optics=CameraOptics(background_gray=18, led_peak_gray=60,
                                                                fiber_diameter_mm=1.3))
    frames = np.stack([sensor.frame() for _ in range(3)])
    centres = sensor.fiber_centres_px
    between = [(round(float(centres[i, 0] + centres[i + 1, 0]) / 2), round(float(centres[i, 1])))
               for i in range(26, 32)]  # half a pitch right of six fibers of the middle row
    with pytest.raises(FiberMapError, match="among the fibers fit no layout fiber.*layout CSV"):
        build_fiber_map(_with_corner_blobs(frames, 60.0, between), layout)
