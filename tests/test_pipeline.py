"""The runtime pipeline on synthetic frames, and its agreement with the reference method.

The calibration bundle is built here directly (synthetic fiber table: fiber i
is a disc of pixels around its transformed layout position), independent of
the fiber-map code.
"""

from __future__ import annotations

import json
import math
from functools import cache

import numpy as np
import pytest

from optitac_edge.calibration.interpolation import build_interpolation_matrix
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.fiber_table import FiberTable
from optitac_edge.core.grid import SurfaceGrid
from optitac_edge.core.image_transform import ImageTransform
from optitac_edge.core.layout import hex_layout
from optitac_edge.core.options import ContactOptions, ContactThresholds
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.devtools.reference import ReferencePipeline
from optitac_edge.errors import FrameMismatchError

LAYOUT = hex_layout()
GRID = SurfaceGrid.over_layout(LAYOUT)
W, H = 160, 120
BACKGROUND = 12


@cache
def _matrix() -> np.ndarray:
    return build_interpolation_matrix(LAYOUT, GRID)


def make_bundle(
    pixel_format: str = "gray",
    width: int = W,
    height: int = H,
    radius_px: int = 2,
    dead: tuple[int, ...] = (),
    thresholds: ContactThresholds | None = None,
    options: ContactOptions | None = None,
) -> CalibrationBundle:
    """A bundle whose fiber i owns a disc of pixels at its transformed position.

    The paper's method (all improvements off) unless ``options`` are given.
    """
    scale = 0.45 * min(width, height) / LAYOUT.radius_mm
    transform = ImageTransform(rotation_deg=10.0, scale_px_per_mm=scale, cx=width / 2, cy=height / 2)
    centres = transform.layout_to_image(LAYOUT.xy_mm)
    dy, dx = np.mgrid[-radius_px:radius_px + 1, -radius_px:radius_px + 1]
    disc = dx**2 + dy**2 <= radius_px**2
    dx, dy = dx[disc], dy[disc]
    cols = np.rint(centres[:, 0])[:, None].astype(np.int64) + dx
    rows = np.rint(centres[:, 1])[:, None].astype(np.int64) + dy
    index = (rows * width + cols).ravel().astype(np.int32)
    assert np.unique(index).size == index.size  # discs do not overlap
    n = LAYOUT.n_fibers
    dead_mask = np.zeros(n, dtype=bool)
    dead_mask[list(dead)] = True
    table = FiberTable(
        height=height, width=width, pixel_format=pixel_format, pixel_index=index,
        pixel_start=np.arange(n + 1, dtype=np.int64) * disc.sum(), centroid_px=centres,
        dead=dead_mask, unmatched_px=np.zeros((0, 2)),
    )
    return CalibrationBundle(layout=LAYOUT, transform=transform, fibers=table, grid=GRID,
                             interpolation=_matrix(), thresholds=thresholds or ContactThresholds(),
                             options=options or ContactOptions.paper())


def rest_levels(seed: int = 0) -> np.ndarray:
    """Per-fiber rest gray levels (uneven, as real fibers)."""
    return np.random.default_rng(seed).uniform(150.0, 220.0, LAYOUT.n_fibers)


def pressed_levels(rest: np.ndarray, x0: float, y0: float, depth: float = 60.0,
                   s_major: float = 1.8, s_minor: float = 1.8, theta_deg: float = 0.0) -> np.ndarray:
    """Fibers near (x0, y0) darkened by an (anisotropic) Gaussian profile, gray levels."""
    t = math.radians(theta_deg)
    d = LAYOUT.xy_mm - (x0, y0)
    u = math.cos(t) * d[:, 0] + math.sin(t) * d[:, 1]
    v = -math.sin(t) * d[:, 0] + math.cos(t) * d[:, 1]
    return rest - depth * np.exp(-0.5 * ((u / s_major) ** 2 + (v / s_minor) ** 2))


def render(bundle: CalibrationBundle, levels: np.ndarray, pixel_format: str | None = None,
           seed: int = 0) -> np.ndarray:
    """A frame whose fiber pixels have gray level ``levels[i]`` (rounded), others BACKGROUND."""
    fmt = pixel_format or bundle.fibers.pixel_format
    lut = np.concatenate([[BACKGROUND], np.clip(np.rint(levels), 0, 255)]).astype(np.uint8)
    y = lut[bundle.fibers.label_image()]
    if fmt == "gray":
        return y
    if fmt == "rgb":
        return np.ascontiguousarray(np.repeat(y[:, :, None], 3, axis=2))
    chroma = np.random.default_rng(seed).integers(0, 256, (y.shape[0] // 2, y.shape[1]), dtype=np.uint8)
    return np.ascontiguousarray(np.concatenate([y, chroma], axis=0))


def run(pipe, frames: list[np.ndarray]) -> list:
    """Every frame at ``1000 * k`` ns: ``((frame, t_ns, baseline_ready), a copy of its primary estimate)``."""
    out = []
    for k, f in enumerate(frames):
        got = (pipe.process_recorded if isinstance(pipe, Pipeline) else pipe.process)(f, 1000 * k)
        out.append(((got.frame, got.t_ns, got.baseline_ready), got.primary.copy()))
    return out


def warm(bundle: CalibrationBundle, rest: np.ndarray, fmt: str | None = None) -> list[np.ndarray]:
    return [render(bundle, rest, fmt, seed=k) for k in range(bundle.baseline_frames)]


# -- baseline, contact, reuse ------------------------------------------------------------


def test_baseline_then_no_contact_at_rest() -> None:
    bundle = make_bundle()
    rest = rest_levels()
    pipe = Pipeline(bundle)
    ests = run(pipe, warm(bundle, rest) + [render(bundle, rest)])
    for k, (seen, e) in enumerate(ests[:5]):
        assert seen == (k, 1000 * k, False)
        assert not e.contact and math.isnan(e.x_mm)
    seen, last = ests[5]
    assert seen[2] and not last.contact
    assert last.area_mm2 == 0.0 and last.strength == 0.0
    assert math.isnan(last.x_mm) and math.isnan(last.major_mm) and np.all(np.isnan(last.hu))
    assert last.shape == "" and math.isnan(last.confidence)
    np.testing.assert_allclose(pipe.baseline.values, np.rint(rest), atol=1e-4)


@pytest.mark.parametrize("x0,y0", [(0.0, 0.0), (3.1, -2.4), (-5.5, 4.0)])
def test_press_centroid(x0: float, y0: float) -> None:
    bundle = make_bundle()
    rest = rest_levels()
    pipe = Pipeline(bundle)
    run(pipe, warm(bundle, rest))
    result = pipe.process_recorded(render(bundle, pressed_levels(rest, x0, y0)), 7)
    e = result.primary
    assert result.baseline_ready and e.contact
    assert e.x_mm == pytest.approx(x0, abs=0.15)
    assert e.y_mm == pytest.approx(y0, abs=0.15)
    assert e.area_mm2 >= bundle.thresholds.min_area_mm2 and e.strength > 0
    assert 0 < e.minor_mm <= e.major_mm < 2.3548 * 1.8  # truncation narrows the profile
    assert np.all(np.isfinite(e.hu))


def test_elongated_press_angle() -> None:
    bundle = make_bundle()
    rest = rest_levels()
    pipe = Pipeline(bundle)
    run(pipe, warm(bundle, rest))
    for theta in (30.0, -55.0, 90.0):
        e = pipe.process_recorded(render(bundle, pressed_levels(rest, 1.0, -0.5, 60.0, 3.0, 1.2, theta)), 0).primary
        assert e.contact
        assert e.major_mm > 1.5 * e.minor_mm
        diff = (e.angle_deg - theta + 90.0) % 180.0 - 90.0
        assert abs(diff) < 3.0


def test_estimate_is_reused_and_copy_is_independent() -> None:
    bundle = make_bundle()
    rest = rest_levels()
    pipe = Pipeline(bundle)
    run(pipe, warm(bundle, rest))
    e1 = pipe.process_recorded(render(bundle, pressed_levels(rest, 2.0, 2.0)), 1).primary
    kept = e1.copy()
    e2 = pipe.process_recorded(render(bundle, rest), 2).primary
    assert e2 is e1 and not e2.contact
    assert kept.contact and kept.hu is not e2.hu and np.all(np.isfinite(kept.hu))
    json.dumps(kept.to_dict())
    assert e2.to_dict()["x_mm"] is None


def test_shape_features_are_log_hu_and_q4_of_the_binarised_contact() -> None:
    from optitac_edge.core.moments import q4_moment

    bundle = make_bundle()
    rest = rest_levels()
    pipe = Pipeline(bundle)
    warmup = run(pipe, warm(bundle, rest))
    assert all(e.features.shape == (8,) and np.all(np.isnan(e.features)) for _, e in warmup)
    q4 = {}
    for name, levels in (("round", pressed_levels(rest, 1.0, -0.5, 60.0, 2.0, 2.0)),
                         ("long", pressed_levels(rest, 1.0, -0.5, 60.0, 3.5, 1.2, 25.0))):
        e = pipe.process_recorded(render(bundle, levels), 1).primary
        assert e.contact and e.features.dtype == np.float64
        np.testing.assert_array_equal(e.features[:7], e.hu)
        # the paper's method: the binarised contact is the surface above the threshold
        assert e.features[7] == pytest.approx(q4_moment(pipe.surface > 0, GRID), rel=1e-8, abs=1e-12)
        q4[name] = e.features[7]
        kept = e.copy()
        assert kept.features is not e.features
        np.testing.assert_array_equal(kept.features, e.features)
        other = type(e)()
        other.assign(e)
        assert other.features is not e.features
        np.testing.assert_array_equal(other.features, e.features)
        assert kept.to_dict()["features"][7] == pytest.approx(e.features[7])
    assert q4["round"] < 0.005 and q4["long"] > 0.02
    e = pipe.process_recorded(render(bundle, rest), 2).primary
    assert not e.contact and np.all(np.isnan(e.features)) and np.all(np.isfinite(kept.features))
    assert e.to_dict()["features"] == [None] * 8


def test_reset_baseline_tares() -> None:
    bundle = make_bundle()
    rest = rest_levels()
    pressed = render(bundle, pressed_levels(rest, -1.0, 1.0))
    pipe = Pipeline(bundle)
    run(pipe, warm(bundle, rest))
    assert pipe.process_recorded(pressed, 0).primary.contact
    pipe.reset_baseline()
    assert not pipe.baseline_ready
    for _ in range(bundle.baseline_frames):
        result = pipe.process_recorded(pressed, 0)
        assert not result.baseline_ready and not result.primary.contact
    result = pipe.process_recorded(pressed, 0)
    assert result.baseline_ready and not result.primary.contact  # the press is the new zero
    assert result.frame == bundle.baseline_frames * 2 + 1


def test_dead_fibers_are_ignored() -> None:
    bundle = make_bundle(dead=(108, 109))
    rest = rest_levels()
    pipe = Pipeline(bundle)
    run(pipe, warm(bundle, rest))
    flicker = rest.copy()
    flicker[[108, 109]] = 0.0  # a broken fiber going dark is no contact
    e = pipe.process_recorded(render(bundle, flicker), 0).primary
    assert not e.contact and e.area_mm2 == 0.0
    np.testing.assert_array_equal(pipe.signal[[108, 109]], 0.0)


def test_truncation_keeps_values_above_threshold() -> None:
    bundle = make_bundle(thresholds=ContactThresholds(threshold=10.0, min_area_mm2=1.0))
    rest = rest_levels()
    pipe = Pipeline(bundle)
    run(pipe, warm(bundle, rest))
    e = pipe.process_recorded(render(bundle, pressed_levels(rest, 1.0, 2.0, 40.0)), 0).primary
    full = bundle.interpolation.astype(np.float64) @ pipe.signal.astype(np.float64)
    surface = pipe.surface.ravel()
    above = full > 10.0
    np.testing.assert_allclose(surface[above], full[above], rtol=1e-5, atol=1e-4)
    assert np.all(surface[~above] == 0.0)
    assert surface.max() > 30.0  # not binarised
    assert e.area_mm2 == pytest.approx(above.sum() * GRID.cell_area_mm2)
    assert e.strength == pytest.approx(surface.sum() * GRID.cell_area_mm2, rel=1e-5)


def test_min_area_gates_contact() -> None:
    bundle = make_bundle(thresholds=ContactThresholds(threshold=6.0, min_area_mm2=500.0))
    rest = rest_levels()
    pipe = Pipeline(bundle)
    run(pipe, warm(bundle, rest))
    e = pipe.process_recorded(render(bundle, pressed_levels(rest, 0.0, 0.0, 60.0)), 0).primary
    assert not e.contact and 0.0 < e.area_mm2 < 500.0 and e.strength > 0.0
    assert math.isnan(e.x_mm) and np.all(np.isnan(e.hu))


# -- frame checks and pixel formats -----------------------------------------------------


def test_frame_mismatch_errors() -> None:
    """The one check of a frame before the pipeline (a recording's: the table's; the service's: FrameCheck)."""
    from optitac_edge.core.frame_check import FrameCheck

    bundle = make_bundle()
    good = render(bundle, rest_levels())
    table = bundle.fibers
    check = FrameCheck(table, good.shape)
    for bad in (good[:-2], good.T.copy(), good.astype(np.float32), render(bundle, rest_levels(), "rgb")):
        with pytest.raises(FrameMismatchError):
            table.check_frame(bad, "gray")
        assert check(bad) == "bad"
    with pytest.raises(FrameMismatchError):
        make_bundle("yuv420").fibers.check_frame(good, "yuv420")
    with pytest.raises(FrameMismatchError):
        ReferencePipeline(bundle).process(good[:-2], 0)
    assert check(good) is None
    assert Pipeline(bundle).process_recorded(good, 0).frame == 0


@pytest.mark.parametrize("compiled", [False, True], ids=["numpy", "kernel"])
def test_process_is_the_one_checked_entry(compiled) -> None:
    """A camera's frame goes through ``Pipeline.process``: a frame of another shape, type or no array at all
    is skipped as BAD (a typed skip, not a string or an exception), a dark or saturated one as DARK or
    SATURATED, before and after the baseline, and a skipped frame changes nothing: the frames after it give
    what they give without it."""
    from optitac_edge.core.frame_engine import Skip

    bundle = make_bundle()
    rest = rest_levels()
    frames = [render(bundle, rest, seed=k) for k in range(bundle.baseline_frames)]
    frames += [render(bundle, pressed_levels(rest, 1.0, -0.5, 60.0), seed=50 + k) for k in range(5)]
    good = frames[0]
    skipped = {Skip.BAD: [good[:-2], good.astype(np.float32), good.T.copy(), None, "frame", good.tolist()],
               Skip.DARK: [np.zeros_like(good)], Skip.SATURATED: [np.full_like(good, 255)]}
    plain = Pipeline(bundle, compiled=compiled)
    checked = Pipeline(bundle, compiled=compiled)
    t = 0
    for k, frame in enumerate(frames):
        if k in (0, len(frames) - 2):  # the skips, before the baseline and during a press
            for why, bad in skipped.items():
                for b in bad:
                    got = checked.process(b, t)
                    assert got is why and got == why.value and str(got) == why.value, (k, why, type(b))
        a, b = plain.process_recorded(frame, t), checked.process(frame, t)
        assert not isinstance(b, Skip)
        assert (b.frame, b.n_contacts, b.baseline_ready) == (a.frame, a.n_contacts, a.baseline_ready)
        assert b.primary.x_mm == a.primary.x_mm or (np.isnan(a.primary.x_mm) and np.isnan(b.primary.x_mm)), k
        t += 16_666_667
    assert checked.result.n_contacts == 1


def test_pixel_formats_agree() -> None:
    rest = rest_levels(4)
    levels = [rest] * 5 + [pressed_levels(rest, 2.5, -1.0, 50.0, 2.2, 1.4, 20.0), rest]
    results = {}
    for fmt in ("gray", "rgb", "yuv420"):
        bundle = make_bundle(fmt)
        results[fmt] = run(Pipeline(bundle), [render(bundle, lv, seed=k) for k, lv in enumerate(levels)])
    for fmt in ("rgb", "yuv420"):
        for (seen_a, a), (seen_b, b) in zip(results["gray"], results[fmt]):
            assert (seen_a, a.contact) == (seen_b, b.contact)
            np.testing.assert_allclose(
                [a.x_mm, a.y_mm, a.major_mm, a.minor_mm, a.angle_deg, a.strength, a.area_mm2],
                [b.x_mm, b.y_mm, b.major_mm, b.minor_mm, b.angle_deg, b.strength, b.area_mm2],
                rtol=1e-4, atol=1e-4,
            )
            np.testing.assert_allclose(a.hu, b.hu, rtol=1e-4, atol=1e-4)
    assert results["gray"][5][1].contact


# -- agreement with the reference method ----------------------------------------------------


@pytest.mark.parametrize("fmt", ["gray", "rgb", "yuv420"])
def test_fast_agrees_with_reference(fmt: str) -> None:
    bundle = make_bundle(fmt, dead=(3,))
    rest = rest_levels(7)
    presses = [
        pressed_levels(rest, 0.4, 0.3, 70.0),
        pressed_levels(rest, -4.0, 2.5, 40.0, 2.6, 1.3, 35.0),
        pressed_levels(rest, 6.0, -5.0, 55.0, 1.5, 1.5),
        pressed_levels(rest, -9.0, 0.0, 60.0, 2.0, 1.0, -70.0),  # at the rim
    ]
    frames = warm(bundle, rest) + [render(bundle, p, seed=9) for p in presses] + [render(bundle, rest)]
    fast, ref = run(Pipeline(bundle), frames), run(ReferencePipeline(bundle), frames)
    for (seen_a, a), (seen_b, b) in zip(fast, ref):
        assert (seen_a, a.contact) == (seen_b, b.contact)
        if not a.contact:
            continue
        assert a.x_mm == pytest.approx(b.x_mm, abs=0.02)
        assert a.y_mm == pytest.approx(b.y_mm, abs=0.02)
        assert a.major_mm == pytest.approx(b.major_mm, rel=0.01)
        assert a.minor_mm == pytest.approx(b.minor_mm, rel=0.01)
        assert a.strength == pytest.approx(b.strength, rel=0.01)
        assert a.area_mm2 == pytest.approx(b.area_mm2, rel=0.01)
        assert abs((a.angle_deg - b.angle_deg + 90) % 180 - 90) < 0.5
        np.testing.assert_allclose(a.hu[:4], b.hu[:4], rtol=0.01)
    assert sum(e.contact for _, e in fast) == len(presses)


# -- end to end with the simulator and the fiber calibration ----------------------------------


def test_end_to_end_simulated_sensor() -> None:
    from optitac_edge import sim
    from optitac_edge.calibration import fibers as calibration

    sensor = sim.SimulatedSensor(seed=1)
    rest = [sensor.frame() for _ in range(5)]
    bundle = calibration.calibrate_fibers(rest, "gray")
    fast, ref = Pipeline(bundle, ContactOptions.paper()), ReferencePipeline(bundle)
    for f in rest:
        fast.process_recorded(f, 0)
        ref.process(f, 0)
    Ind = sim.Indenter
    cases = [Ind("circle", 2.0, -1.0, 0.0, 4.0, 2.0), Ind("ellipse", -4.0, 3.0, 30.0, 7.0, 2.0),
             Ind("edge", 0.0, 0.0, -40.0, 2.0, 2.0), Ind("square", 5.0, 4.0, 20.0, 5.0, 2.5),
             Ind("triangle", -3.0, -5.0, 0.0, 6.0, 2.0)]
    for ind in cases:
        frame = sensor.frame([ind])
        a, b = fast.process_recorded(frame, 0).primary.copy(), ref.process(frame, 0).primary
        assert a.contact and b.contact, ind
        assert a.x_mm == pytest.approx(b.x_mm, abs=0.02) and a.y_mm == pytest.approx(b.y_mm, abs=0.02)
        assert a.major_mm == pytest.approx(b.major_mm, rel=0.01)
        assert a.minor_mm == pytest.approx(b.minor_mm, rel=0.01)
        assert math.hypot(a.x_mm - ind.x_mm, a.y_mm - ind.y_mm) < 0.4, ind
        if ind.shape in ("ellipse", "edge"):
            assert abs((a.angle_deg - ind.angle_deg + 90) % 180 - 90) < 3.0, ind
    for _ in range(3):
        assert not fast.process_recorded(sensor.frame(), 0).primary.contact


@pytest.mark.parametrize("options", [ContactOptions.paper(), ContactOptions()], ids=["paper", "default"])
def test_shape_features_equal_the_plain_moments_of_the_binarised_contact(options: ContactOptions) -> None:
    """The runtime's OpenCV-moment route to log-Hu and q4 against the plain numpy functions.

    The reference method has no q4, so this is the oracle for ``features[7]``.
    """
    from optitac_edge.core.moments import hu_moments, log_hu, q4_moment

    bundle = make_bundle("gray", options=options)
    rest = rest_levels(7)
    presses = [pressed_levels(rest, -4.0, 2.5, 40.0, 2.6, 1.3, 35.0),
               pressed_levels(rest, 3.0, -2.0, 55.0, 1.5, 1.5)]
    pipe = Pipeline(bundle)
    run(pipe, warm(bundle, rest))
    for levels in presses:
        est = pipe.process_recorded(render(bundle, levels, seed=9), 10**9).primary
        assert est.contact
        surface = pipe.surface
        trunc = np.float32(pipe.levels.as_tuple()[0])
        if options.shape_fraction > 0:
            level = np.float32(max(float(trunc), options.shape_fraction * float(surface.max())))
        else:  # the paper: the cells above the truncation level
            level = trunc
        binary = surface > level
        np.testing.assert_allclose(est.hu, log_hu(hu_moments(binary, bundle.grid)), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(est.features[:7], est.hu)
        assert est.features[7] == pytest.approx(q4_moment(binary, bundle.grid), rel=1e-8, abs=1e-14)


def test_single_threaded_opencv_restores_the_thread_count() -> None:
    import cv2

    from optitac_edge.core.pipeline import single_threaded_opencv

    before = cv2.getNumThreads()
    with single_threaded_opencv():
        assert cv2.getNumThreads() == 1
    assert cv2.getNumThreads() == before
    with pytest.raises(RuntimeError), single_threaded_opencv():
        raise RuntimeError("boom")
    assert cv2.getNumThreads() == before


@pytest.mark.parametrize("n_contacts", [1, 4])
def test_a_frame_makes_no_array_sized_temporary_even_with_four_contacts(bundle_path, n_contacts: int) -> None:
    """Gross, not only net: the largest allocation alive within a frame stays far below an array of the
    frame's data (the fiber pixels, 21 kB; a mesh box, 10-40 kB). Before, the fiber sums cast 43 kB, a
    contact's masked surface 65 kB and every ufunc on a strided box view copied it."""
    import tracemalloc

    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.sim.multi_press import multi_press_frames

    bundle = load_bundle(bundle_path)
    frames = multi_press_frames(n_contacts, 12, 12, seed=n_contacts)
    pipe = Pipeline(bundle)
    t = 0
    for f in frames * 2:  # baseline, then every frame once: OpenCV's and numpy's caches warm
        pipe.process_recorded(f, t)
        t += 4_166_667
    largest = 0
    tracemalloc.start()
    try:
        for f in frames[12:]:
            tracemalloc.reset_peak()
            before = tracemalloc.get_traced_memory()[0]
            result = pipe.process_recorded(f, t)
            largest = max(largest, tracemalloc.get_traced_memory()[1] - before)
            t += 4_166_667
    finally:
        tracemalloc.stop()
    assert result.n_contacts == n_contacts
    assert largest < 6000, largest  # Python objects (OpenCV's moments dict: 2.3 kB), index arrays
