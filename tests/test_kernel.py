"""The compiled per-frame kernel (kernel/*.c) against the numpy pipeline, its readable reference.

Every frame is run through both (``Pipeline(compiled=False)`` and ``compiled=True``) and the
results compared: identical contact counts, ids, touches, releases, shapes and flags; the fiber
means and the signal bit for bit (the same float32 steps); the surface, centroid and widths to
rounding (the kernel sums the gradient product and the moments in another order than OpenBLAS
and OpenCV: 1e-6 mm allowed, 1e-3 degrees for the angle). The frames: the simulated sensor with
0-4 presses (the four join into one blob: the nearest-seed split), LED dimming and
brightening, a start during a press (the baseline raise), a tare, the MCU's contact level; every
contact option switched; gray, RGB and YUV frames; dead fibers; a dense surface matrix; and a
small layout of large fibers (sums past 16 bits).
"""

from __future__ import annotations

import dataclasses
import math
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from optitac_edge.calibration.bundle_models import (
    with_centroid_map,
    with_depth_model,
    with_shape_model,
    with_width_model,
)
from optitac_edge.calibration.interpolation import build_interpolation_matrix
from optitac_edge.calibration.shape_fit import ShapeFitSettings, fit_shape_model
from optitac_edge.core import _frame_kernel, compiled, gradient_solve
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.centroid_map import CentroidErrorMap
from optitac_edge.core.compiled import CompiledEngine
from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.depth_model import DepthForceModel, RadialMonotoneMap
from optitac_edge.core.fiber_table import FiberTable
from optitac_edge.core.frame_engine import Skip
from optitac_edge.core.grid import SurfaceGrid
from optitac_edge.core.image_transform import ImageTransform
from optitac_edge.core.layout import hex_layout
from optitac_edge.core.options import ContactOptions
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.core.width_model import AxisMap, WidthModel
from optitac_edge.io.bundle_file import load_bundle
from optitac_edge.sim.multi_press import multi_press_frames
from optitac_edge.sim.synthetic_shapes import synthetic_features

PERIOD = 4_166_667  # ns, 240 fps
MM = 1e-6  # centroid and widths, mm
DEG = 1e-3  # angle, degrees


# -- the comparison ----------------------------------------------------------------------------------


def _close(a: float, b: float, tol: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol


def assert_same_frame(ref: Pipeline, kern: Pipeline, where: str) -> None:
    """The two pipelines' last frames agree (see the module docstring)."""
    a, b = ref.result, kern.result
    assert (a.frame, a.t_ns, a.baseline_ready, a.n_contacts, a.releases(), a.light_changed, a.baseline_raised,
            a.raised_fibers) == \
        (b.frame, b.t_ns, b.baseline_ready, b.n_contacts, b.releases(), b.light_changed, b.baseline_raised,
         b.raised_fibers), where
    assert np.array_equal(ref.means, kern.means), where
    if not ref.baseline_ready:
        return
    assert np.array_equal(ref.signal, kern.signal), where
    np.testing.assert_allclose(kern.surface, ref.surface, rtol=1e-5, atol=1e-5 * float(ref.levels.trunc) + 1e-7,
                               err_msg=where)
    np.testing.assert_array_equal(ref.baseline.values, kern.baseline.values, err_msg=where)
    for i in range(max(a.n_contacts, 1)):
        x, y = a.contacts[i], b.contacts[i]
        assert (x.contact, x.contact_id, x.touch_frame, x.shape) == (y.contact, y.contact_id, y.touch_frame, y.shape), \
            where
        edge = x.contact and _borderline(ref, kern, x.peak, y.peak)
        mm, rel = (EDGE_MM, EDGE_REL) if edge else (MM, 1e-5)
        for name in ("x_mm", "y_mm", "major_mm", "minor_mm"):
            assert _close(getattr(x, name), getattr(y, name), mm), (where, name, getattr(x, name), getattr(y, name))
        for name in ("depth_mm", "force_n"):  # from the strength (gray levels * mm^2 in gray-level mode): relative
            v, w = getattr(x, name), getattr(y, name)
            assert _close(v, w, (rel if edge else 1e-6) * max(abs(v), 1.0)), (where, name, v, w)
        if edge:  # a near-round contact's angle swings with one cell: its ellipse's covariance does not
            np.testing.assert_allclose(_covariance(y), _covariance(x), atol=EDGE_REL * x.major_mm ** 2, err_msg=where)
        elif not math.isnan(x.angle_deg):
            assert abs((x.angle_deg - y.angle_deg + 90.0) % 180.0 - 90.0) <= DEG, (where, x.angle_deg, y.angle_deg)
        for name in ("strength", "area_mm2", "peak", "confidence"):
            v, w = getattr(x, name), getattr(y, name)
            assert _close(v, w, rel * max(abs(v), 1e-9)), (where, name, v, w)
        np.testing.assert_allclose(y.features, x.features, rtol=rel if edge else 1e-6, atol=1e-9, err_msg=where)
        np.testing.assert_array_equal(np.isnan(x.hu), np.isnan(y.hu), err_msg=where)


#: A contact with a surface cell on one of its levels to within the two surfaces' rounding (the surface is
#: compared to 1e-5, and each pipeline sets its peak-fraction levels from its own peak): that one cell may weigh
#: in one pipeline and not the other, moving the moments by up to its share of them (a cell of the contact's
#: hundred or more): centroid and widths within 0.02 mm, the ellipse's covariance, strength, area and shape
#: features within 2 %.
EDGE_MM, EDGE_REL = 0.02, 0.02


def _covariance(c: ContactEstimate) -> np.ndarray:
    """The contact's ellipse as a covariance matrix (FWHM units): ``R diag(major², minor²) Rᵀ``."""
    t = math.radians(c.angle_deg)
    r = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    return r @ np.diag([c.major_mm ** 2, c.minor_mm ** 2]) @ r.T


def _borderline(ref: Pipeline, kern: Pipeline, peak_ref: float, peak_kern: float) -> bool:
    """Whether a cell of the numpy surface lies, to within the surfaces' rounding, between the two pipelines'
    versions of a level the contact's moments or shape features are taken at (truncation, peak fraction,
    shape fraction)."""
    trunc, o = float(ref.levels.trunc), ref.options
    surface = ref.surface
    for fraction in (0.0, o.peak_fraction, o.shape_fraction):
        lo = min(max(trunc, fraction * peak_ref), max(trunc, fraction * peak_kern))
        hi = max(max(trunc, fraction * peak_ref), max(trunc, fraction * peak_kern))
        eps = 1e-5 * hi + 1e-5 * trunc + 1e-7
        if np.any((surface >= lo - eps) & (surface <= hi + eps)):
            return True
    return False


def _engine(pipe: Pipeline) -> CompiledEngine:
    """The compiled engine of ``pipe`` (which must run one)."""
    assert isinstance(pipe.engine, CompiledEngine)
    return pipe.engine


def run_both(bundle: CalibrationBundle, frames: list[np.ndarray], options: ContactOptions | None = None,
             events: dict[int, str] | None = None) -> tuple[Pipeline, Pipeline, list[tuple[int, bool]]]:
    """Both pipelines over ``frames`` (``events``: frame -> "tare" or "level"), compared frame by frame;
    each frame's (contacts, baseline raised)."""
    ref, kern = Pipeline(bundle, options, compiled=False), Pipeline(bundle, options, compiled=True)
    assert not ref.compiled and kern.compiled
    seen = []
    #: Each frame's primary contact of the numpy pipeline (a copy), for the tests' own checks.
    run_both.primaries = []  # type: ignore[attr-defined]
    for k, frame in enumerate(frames):
        what = (events or {}).get(k)
        for p in (ref, kern):
            if what == "tare":
                p.reset_baseline()
            elif what == "level":
                p.set_contact_level(0.02)
            p.process_recorded(frame, k * PERIOD)
        assert_same_frame(ref, kern, f"frame {k}")
        seen.append((ref.result.n_contacts, ref.result.baseline_raised))
        run_both.primaries.append(ref.result.primary.copy())  # type: ignore[attr-defined]
    return ref, kern, seen


# -- bundles and frames --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def modelled(bundle_path) -> CalibrationBundle:
    """The simulated sensor's fiber map with every calibration model the kernel evaluates."""
    bundle = load_bundle(bundle_path)
    rng = np.random.default_rng(0)
    n = 60
    yy, xx = np.mgrid[0:n, 0:n] / n
    ex = (0.3 * np.sin(3 * xx) * np.cos(2 * yy) + 0.01 * rng.normal(size=(n, n))).astype(np.float32)
    ey = (0.2 * np.cos(4 * xx + yy)).astype(np.float32)
    bundle = with_centroid_map(bundle, CentroidErrorMap(-13.0, -13.0, 26.0 / (n - 1), ex, ey))
    major = AxisMap(np.array([1.0, 3.0, 6.0, 12.0]), np.array([0.5, 2.5, 6.5, 13.0]))
    minor = AxisMap(np.array([1.0, 4.0, 11.0]), np.array([0.8, 3.5, 12.0]))
    bundle = with_width_model(bundle, WidthModel("monotone", major, minor, 0.1, -0.05, 12.0))
    depth = RadialMonotoneMap(0.3, 12.0, AxisMap(np.array([0.5, 2.0, 8.0]), np.array([0.1, 1.0, 3.5])), power=4)
    force = RadialMonotoneMap(-0.2, 12.0, AxisMap(np.array([0.01, 0.2, 1.0]), np.array([0.0, 2.0, 8.0])), power=2)
    bundle = with_depth_model(bundle, DepthForceModel("width", depth, force, "root_strength_width"))
    feats, labels = synthetic_features(12, seed=3)
    # the subset a full search picks on these features (4 s more per test worker to search it again)
    shapes = fit_shape_model(feats, labels, settings=ShapeFitSettings(seed=0, holdout=0.3, cv_folds=2,
                                                                      subsets=((0, 1, 2, 7),)))
    assert shapes.model.kind == "gmm_unsupervised"
    return with_shape_model(bundle, shapes.model)


def sim_frames(bundle: CalibrationBundle, contacts: int, n: int, rest: int, seed: int) -> list[np.ndarray]:
    return multi_press_frames(contacts, n, rest, layout=bundle.layout, fps=240.0, seed=seed)


def scaled(frames: list[np.ndarray], start: float, end: float) -> list[np.ndarray]:
    """The frames with the light scaled from ``start`` to ``end`` (an LED dimming or brightening)."""
    out = []
    for k, f in enumerate(frames):
        g = start + (end - start) * k / max(len(frames) - 1, 1)
        out.append(np.clip(np.rint(f.astype(np.float32) * g), 0, 255).astype(np.uint8))
    return out


@pytest.fixture(scope="module")
def day(modelled) -> list[np.ndarray]:
    """Rest, then 1, 2 and 4 presses, a quick LED step down and a slow dimming with presses."""
    one = sim_frames(modelled, 1, 60, 30, seed=1)
    two = sim_frames(modelled, 2, 50, 3, seed=2)
    four = sim_frames(modelled, 4, 50, 3, seed=4)
    dim = scaled(sim_frames(modelled, 1, 40, 20, seed=5), 1.0, 0.93)
    step = scaled(sim_frames(modelled, 0, 0, 12, seed=6), 0.93, 0.93) + scaled(sim_frames(modelled, 0, 0, 8, seed=7),
                                                                                 1.02, 1.02)
    return one + two + four + dim + step


# -- parity ----------------------------------------------------------------------------------------------


def test_the_kernel_is_built() -> None:
    """CI builds it (``pip install``); the parity tests below need it."""
    assert compiled.kernel_status() == (True, "the compiled kernel runs the frames")
    assert _frame_kernel.FIELDS == compiled.fields() == 20


def test_a_day_of_presses_with_every_model_agrees(modelled, day) -> None:
    _ref, kern, seen = run_both(modelled, day, events={150: "level", 230: "tare"})
    assert kern.compiled and _engine(kern).corrects  # the kernel applied the models
    assert {0, 1, 2, 4} <= {n for n, _ in seen}  # every count the day was made to hold (4 joined may split in 3)
    touching = [e for e in run_both.primaries if e.contact]  # type: ignore[attr-defined]
    assert {e.shape for e in touching} - {""}  # the shape model classified
    assert all(not math.isnan(e.depth_mm) and not math.isnan(e.force_n) for e in touching)


OPTIONS = {
    "paper": ContactOptions.paper(),
    "gray levels": {"relative": False},
    "paper levels": {"noise_levels": False},
    "no hysteresis": {"hysteresis": False},
    "no peak fraction": {"peak_fraction": 0.0},
    "no shape fraction": {"shape_fraction": 0.0},
    "one contact": {"max_contacts": 1},
    "two contacts": {"max_contacts": 2},
    "no tracking": {"track_baseline": False},
    "no gain": {"compensate_gain": False},
    "no gain, gray levels": {"compensate_gain": False, "relative": False},
    "holdoff": {"holdoff_s": 0.05},
    "neighbour support": {"support": True},
}


@pytest.mark.parametrize("name", list(OPTIONS))
def test_every_option_agrees(modelled, day, name) -> None:
    base = modelled.options
    o = OPTIONS[name]
    options = o if isinstance(o, ContactOptions) else dataclasses.replace(base, **o)
    run_both(modelled, day[::2], options)


def test_a_start_during_a_press_raises_the_same_fibers(modelled) -> None:
    """The baseline is taken over a press; after the release both raise the same fibers at the same frame."""
    pressed = sim_frames(modelled, 1, 40, 0, seed=8)
    frames = pressed + sim_frames(modelled, 0, 0, 120, seed=9) + sim_frames(modelled, 1, 30, 0, seed=8)
    _, _, seen = run_both(modelled, frames)
    assert sum(raised for _, raised in seen) >= 1  # both raised, in the same frame (compared above)


def test_dead_fibers_filled_and_not(modelled, day) -> None:
    dead = np.zeros(modelled.fibers.n_fibers, dtype=bool)
    dead[[0, 40, 76, 105, 200]] = True
    bundle = modelled.with_updates(fibers=dataclasses.replace(modelled.fibers, dead=dead))
    run_both(bundle, day[::3])
    run_both(bundle, day[::3], dataclasses.replace(bundle.options, fill_dead=False))


def test_bands_of_noise_and_of_drift_agree(modelled, day) -> None:
    """Fibers banded by their noise (the garrote), by their drift (the shift) and by both, with an on level
    chosen and with levels from the noise: the kernel's bands are the numpy pipeline's, frame by frame."""
    from optitac_edge.core.levels import DRIFT_KEY, LEVELS_KEY, NOISE_KEY

    n = modelled.fibers.n_fibers
    rng = np.random.default_rng(7)
    noise = np.full(n, 0.4, dtype=np.float32)
    drift = np.full(n, 0.004, dtype=np.float32)
    noise[rng.choice(n, 30, replace=False)] *= rng.uniform(3, 8, 30).astype(np.float32)
    drift[rng.choice(n, 30, replace=False)] *= rng.uniform(3, 8, 30).astype(np.float32)
    bundle = modelled.with_updates(extra_arrays={**modelled.extra_arrays, NOISE_KEY: noise, DRIFT_KEY: drift},
                                   extra_meta={**modelled.extra_meta,
                                               LEVELS_KEY: {"noise_samples": 100, "drift_samples": 100}})
    options = dataclasses.replace(bundle.options, noise_levels=True, relative=True)
    for on_level in (0.0, 0.04):
        ref, _kern, _seen = run_both(bundle, day[::2], dataclasses.replace(options, on_level=on_level))
        bands = ref.levels.bands
        assert bands is not None
        assert np.count_nonzero(bands[0]) >= 20 and np.count_nonzero(bands[1]) >= 20  # both kinds: c^2, shift
        assert np.count_nonzero((bands[0] > 0) & (bands[1] > 0)) >= 1


@pytest.fixture()
def solve_always(monkeypatch) -> None:
    """The kernel finds the gradients by the sparse solve whatever the cost and size (217 fibers take it
    already, by the operator's bytes; a 1027-fiber bundle takes a minute to calibrate)."""
    monkeypatch.setattr(gradient_solve, "SOLVE_WEIGHT", 0)


def test_the_gradient_solve_agrees(modelled, day, solve_always) -> None:
    """The gradients by the sparse solve (a 1027-fiber sensor's kernel) give the numpy pipeline's contacts,
    with and without dead fibers filled."""
    assert "gs_fibers" in _engine(Pipeline(modelled, compiled=True)).plan.as_dict()
    _ref, _kern, seen = run_both(modelled, day[:160])
    assert {0, 1, 2, 4} <= {n for n, _ in seen}  # every count the day was made to hold (4 joined may split in 3)
    dead = np.zeros(modelled.fibers.n_fibers, dtype=bool)
    dead[[0, 40, 76, 105, 200]] = True
    bundle = modelled.with_updates(fibers=dataclasses.replace(modelled.fibers, dead=dead))
    assert "gs_fibers" in _engine(Pipeline(bundle, compiled=True)).plan.as_dict()
    run_both(bundle, day[:160:2])


def test_the_gradient_solve_is_chosen_where_the_dense_operator_is_large(modelled, monkeypatch) -> None:
    """217 fibers: the solve (the dense operator's 368 KB are more than DENSE_BYTES_MAX, though its 94 k
    multiply-adds are fewer than the solve's ~35 k at 4 times the cost each); with a budget that holds the
    operator, the dense product."""
    gs = Pipeline(modelled, compiled=False).parts.surface_op.gradient_solve  # type: ignore[union-attr]
    solve = gs()
    assert solve is not None and gradient_solve.dense_bytes(217) == 376_712
    assert "gs_fibers" in _engine(Pipeline(modelled, compiled=True)).plan.as_dict()
    monkeypatch.setattr(gradient_solve, "DENSE_BYTES_MAX", 400_000)
    assert gs() is None
    assert "gs_fibers" not in _engine(Pipeline(modelled, compiled=True)).plan.as_dict()


def test_the_onnx_or_no_corrector_runs_in_python(modelled, day) -> None:
    """A corrector the kernel was not built with (here: none, then a fresh one) is applied in Python."""
    ref, kern = Pipeline(modelled, compiled=False), Pipeline(modelled, compiled=True)
    for p in (ref, kern):
        p.set_corrector(None)
    for k, f in enumerate(day[:120]):
        ref.process_recorded(f, k * PERIOD)
        kern.process_recorded(f, k * PERIOD)
        assert_same_frame(ref, kern, f"frame {k}")
    assert not _engine(kern).corrects
    from optitac_edge.core.corrections import ContactCorrector

    other = ContactCorrector(modelled)
    for p in (ref, kern):
        p.set_corrector(other)
    assert not _engine(kern).corrects  # not the kernel's own: applied per contact in Python
    for k, f in enumerate(day[120:200]):
        ref.process_recorded(f, (120 + k) * PERIOD)
        kern.process_recorded(f, (120 + k) * PERIOD)
        assert_same_frame(ref, kern, f"frame {120 + k}")


# -- gray, RGB and YUV frames; a dense matrix; large fibers ---------------------------------------------------


def synthetic_bundle(fmt: str, rings: int = 8, width: int = 160, height: int = 120, radius_px: int = 2,
                     dead: tuple[int, ...] = ()) -> CalibrationBundle:
    """A bundle whose fiber i owns a disc of pixels at its transformed position (a dense surface matrix)."""
    layout = hex_layout(rings)
    grid = SurfaceGrid.over_layout(layout, 60)
    scale = 0.45 * min(width, height) / layout.radius_mm
    transform = ImageTransform(rotation_deg=10.0, scale_px_per_mm=scale, cx=width / 2, cy=height / 2)
    centres = transform.layout_to_image(layout.xy_mm)
    dy, dx = np.mgrid[-radius_px:radius_px + 1, -radius_px:radius_px + 1]
    disc = dx ** 2 + dy ** 2 <= radius_px ** 2
    cols = np.rint(centres[:, 0])[:, None].astype(np.int64) + dx[disc]
    rows = np.rint(centres[:, 1])[:, None].astype(np.int64) + dy[disc]
    n = layout.n_fibers
    dead_mask = np.zeros(n, dtype=bool)
    dead_mask[list(dead)] = True
    table = FiberTable(height=height, width=width, pixel_format=fmt,
                       pixel_index=(rows * width + cols).ravel().astype(np.int32),
                       pixel_start=np.arange(n + 1, dtype=np.int64) * int(disc.sum()), centroid_px=centres,
                       dead=dead_mask, unmatched_px=np.zeros((0, 2)))
    return CalibrationBundle(layout=layout, transform=transform, fibers=table, grid=grid,
                             interpolation=build_interpolation_matrix(layout, grid),
                             options=dataclasses.replace(ContactOptions(), black_level=12.0, noise_rel=0.002))


def synthetic_frames(bundle: CalibrationBundle, n: int, seed: int) -> list[np.ndarray]:
    """Rest, then a press wandering over the array and a second one, on a noisy fiber light."""
    rng = np.random.default_rng(seed)
    layout, table = bundle.layout, bundle.fibers
    rest = rng.uniform(150.0, 215.0, layout.n_fibers)
    labels = table.label_image()
    frames = []
    for k in range(n):
        levels = rest + rng.normal(0.0, 0.6, rest.size)
        if k >= 8:
            for j, (x0, y0) in enumerate([(3 * math.cos(k / 9), 3 * math.sin(k / 7)), (-4.0, 2.0)][:1 + (k % 3 == 0)]):
                d = layout.xy_mm - (x0, y0)
                levels -= (40 + 10 * j) * np.exp(-0.5 * (d ** 2).sum(axis=1) / 1.9 ** 2)
        lut = np.concatenate([[12.0], np.clip(np.rint(levels), 0, 255)]).astype(np.uint8)
        y = lut[labels]
        if table.pixel_format == "gray":
            frames.append(y)
        elif table.pixel_format == "rgb":  # colours whose BT.601 gray is near the level: every weight matters
            rgb = np.stack([y, np.clip(y.astype(int) + rng.integers(-30, 31, y.shape), 0, 255),
                            np.clip(y.astype(int) - rng.integers(-30, 31, y.shape), 0, 255)], axis=2)
            frames.append(np.ascontiguousarray(rgb.astype(np.uint8)))
        else:
            chroma = rng.integers(0, 256, (y.shape[0] // 2, y.shape[1]), dtype=np.uint8)
            frames.append(np.ascontiguousarray(np.concatenate([y, chroma])))
    return frames


@pytest.mark.parametrize("fmt", ["gray", "rgb", "yuv420"])
def test_pixel_formats_and_a_dense_matrix_agree(fmt) -> None:
    bundle = synthetic_bundle(fmt, dead=(5, 60))
    assert bundle.surface_factors is None  # the dense surface, in both
    run_both(bundle, synthetic_frames(bundle, 60, seed=1))


@pytest.mark.parametrize("mix", ["green", "red", "mean"])
def test_a_colour_mix_agrees(mix) -> None:
    """RGB frames read through another colour mix than luma (issue 37): the kernel's fixed-point weights give
    the numpy sampler's means to the bit, and the same contacts."""
    bundle = synthetic_bundle("rgb", dead=(5, 60))
    bundle = bundle.with_updates(options=dataclasses.replace(bundle.options, colour_mix=mix))
    ref, kern, _ = run_both(bundle, synthetic_frames(bundle, 40, seed=5))
    assert "rgb_weights" in _engine(kern).plan.as_dict()
    luma = Pipeline(synthetic_bundle("rgb", dead=(5, 60)), compiled=False)
    frame = synthetic_frames(bundle, 1, seed=5)[0]
    assert not np.array_equal(luma.parts.sampler.means(frame, np.zeros(217, np.float32)),
                              ref.parts.sampler.means(frame, np.zeros(217, np.float32)))


def _centres_at(frame: np.ndarray, table: FiberTable, which: np.ndarray, value: int) -> np.ndarray:
    """``frame`` with the centre pixel (every byte of it) of the fibers ``which`` set to ``value``."""
    out = frame.copy()
    col = np.clip(np.rint(table.centroid_px[which, 0]), 0, table.width - 1).astype(int)
    row = np.clip(np.rint(table.centroid_px[which, 1]), 0, table.height - 1).astype(int)
    out[row, col] = value
    return out


@pytest.mark.parametrize("fmt", ["gray", "rgb", "yuv420"])
def test_the_kernels_frame_check_is_framechecks(fmt) -> None:
    """Pipeline.process: the kernel checks after the fiber means (the frame then in the caches), the
    numpy pipeline with FrameCheck first; the same verdicts and saturated flags, and a frame refused changes
    nothing (the next frames agree)."""
    bundle = synthetic_bundle(fmt, dead=(5, 60))
    table, n = bundle.fibers, bundle.fibers.n_fibers
    frames = synthetic_frames(bundle, 40, seed=3)
    live = np.flatnonzero(~table.dead)
    f = frames[20]
    luma = f[:table.height] if fmt == "yuv420" else f
    variants = {
        "dark": np.zeros_like(f), "one centre bright": _centres_at(np.zeros_like(f), table, live[:1], 200),
        "a tenth bright": _centres_at(np.zeros_like(f), table, live[:len(live) // 10 + 1], 9),
        "all full scale": np.full_like(f, 255), "some centres full scale": _centres_at(f, table, live[:7], 255),
        "half the centres at full scale": _centres_at(f, table, live[:len(live) // 2], 255),
        "more than half": _centres_at(f, table, live[:len(live) // 2 + 1], 255),
        "dead fibers at full scale": _centres_at(f, table, np.array([5, 60]), 255),
    }
    assert luma.shape[:2] == (table.height, table.width) and n == len(live) + 2
    ref, kern = Pipeline(bundle, compiled=False), Pipeline(bundle, compiled=True)
    seen = set()
    for k, frame in enumerate(frames[:20] + list(variants.values()) + frames[20:]):
        name = next((v for v, a in variants.items() if a is frame), f"frame {k}")
        assert kern.baseline.ready or k < 20  # the variants go through the kernel's check
        a, b = ref.process(frame, k * PERIOD), kern.process(frame, k * PERIOD)
        assert (a if isinstance(a, Skip) else None) == (b if isinstance(b, Skip) else None), name
        seen.add(a if isinstance(a, Skip) else ("saturated flag" if ref.result.saturated else "ok"))
        if not isinstance(a, Skip):
            assert ref.result.saturated == kern.result.saturated, name
            assert_same_frame(ref, kern, name)
    assert seen == {"dark", "saturated", "saturated flag", "ok"}


def test_large_fibers_sum_past_sixteen_bits() -> None:
    """19 fibers of 1,257 pixels each (more than 128 eight-byte chunks, sums over 65,535): failed with
    the first gray gather, which added its 16-bit lanes with a multiply that overflowed."""
    bundle = synthetic_bundle("gray", rings=2, width=640, height=480, radius_px=20)
    assert int(bundle.fibers.pixel_count.min()) > 1024
    frames = synthetic_frames(bundle, 30, seed=2)
    ref, kern, _ = run_both(bundle, frames)
    assert float(ref.means.min()) * int(bundle.fibers.pixel_count.min()) > 0xFFFF  # every fiber's sum is past 16 bits
    assert kern.result.n_contacts >= 1


# -- the kernel's own parts --------------------------------------------------------------------------------


def test_the_sort_sorts() -> None:
    rng = np.random.default_rng(0)
    for n in (0, 1, 2, 3, 16, 17, 100, 217, 1027):
        for values in (rng.normal(size=n), np.round(rng.normal(size=n), 1), np.zeros(n), np.arange(n)[::-1]):
            a = values.astype(np.float32)
            _frame_kernel.sort(a)
            assert np.array_equal(a, np.sort(values.astype(np.float32)))


def test_the_labelling_is_opencvs_partition_in_raster_order() -> None:
    rng = np.random.default_rng(1)
    for k in range(60):
        h, w = rng.integers(1, 40, 2)
        mask = (rng.random((h, w)) < rng.uniform(0.1, 0.7)).astype(np.uint8)
        labels = np.zeros((h, w), dtype=np.int32)
        n = _frame_kernel.label8(mask, labels)
        n_cv, cv_labels = cv2.connectedComponents(mask, connectivity=8, ltype=cv2.CV_32S)
        assert n == n_cv, k
        pairs = set(zip(labels[mask > 0].tolist(), cv_labels[mask > 0].tolist()))
        assert len(pairs) == n - 1  # one to one: the same components
        firsts = [int(np.flatnonzero(labels.ravel() == lab)[0]) for lab in range(1, n)]
        assert firsts == sorted(firsts)  # numbered in raster order of their first cell


def test_the_nearest_seed_is_opencvs_labelled_distance_transform() -> None:
    """The split of joined presses: every cell to the seed component cv2.distanceTransformWithLabels gives it."""
    rng = np.random.default_rng(2)
    for k in range(80):
        h, w = (int(v) for v in rng.integers(2, 45, 2))
        seeds = np.zeros((h, w), dtype=np.uint8)
        for _ in range(int(rng.integers(1, 6))):  # a few blobs of seeds
            y, x, r = int(rng.integers(0, h)), int(rng.integers(0, w)), int(rng.integers(0, 4))
            seeds[max(y - r, 0):y + r + 1, max(x - r, 0):x + r + 1] = 1
        seeds &= (rng.random((h, w)) < 0.9).astype(np.uint8)  # ragged
        if not seeds.any():
            continue
        labels = np.zeros((h, w), dtype=np.int32)
        _frame_kernel.label8(seeds, labels)
        nearest = np.zeros((h, w), dtype=np.int32)
        _frame_kernel.nearest_seed(labels, nearest)
        _dist, cv_nearest = cv2.distanceTransformWithLabels((1 - seeds).astype(np.uint8), cv2.DIST_L2, 3,
                                                            labelType=cv2.DIST_LABEL_CCOMP)
        mapping = dict(zip(labels[seeds > 0].tolist(), cv_nearest[seeds > 0].tolist()))  # the two numberings
        assert len(set(mapping.values())) == len(mapping), k
        np.testing.assert_array_equal(np.vectorize(mapping.get)(nearest), cv_nearest, err_msg=str(k))


def test_a_bad_plan_is_one_clear_error(modelled) -> None:
    pipe = Pipeline(modelled, compiled=True)
    plan = {**pipe.parts.sampler.kernel_arrays(), **pipe.parts.surface_op.kernel_arrays()}
    with pytest.raises(KeyError, match="kernel plan: missing n_fibers"):
        _frame_kernel.Kernel(plan)
    with pytest.raises(TypeError):
        _frame_kernel.Kernel("not a dict")


def test_a_plan_key_the_kernel_does_not_read_is_refused(modelled) -> None:
    """The plan is typed (KernelPlan) and the kernel refuses a key it does not read: a misspelt or stale key
    is one clear error, not a setting silently ignored."""
    plan = _engine(Pipeline(modelled, compiled=True)).plan
    good = plan.as_dict()
    _frame_kernel.Kernel(good)
    for key in ("split_fracton", "tri_colz", "cmap_typo"):
        with pytest.raises(KeyError, match=f"kernel plan: unknown key {key}"):
            _frame_kernel.Kernel({**good, key: 1})
    with pytest.raises(KeyError, match="not a string"):
        _frame_kernel.Kernel({**good, 3: 1})
    clash = dataclasses.replace(plan, check={**plan.check, "pixel_index": plan.sampler["pixel_index"]})
    with pytest.raises(ValueError, match="check gives pixel_index again"):
        clash.as_dict()


def test_the_kernels_constants_and_names_are_the_pythons() -> None:
    """What C and Python must agree on is read from the module, not copied by comment: the contact fields'
    names (the engine reads each by name), the most contacts and the surface's terms per cell."""
    from optitac_edge.core.contact_finder import MAX_CANDIDATES
    from optitac_edge.core.options import MAX_CONTACTS
    from optitac_edge.core.surface import CELL_TERMS

    assert _frame_kernel.MAX_CANDIDATES == MAX_CANDIDATES >= MAX_CONTACTS
    assert _frame_kernel.CELL_TERMS == CELL_TERMS
    assert len(_frame_kernel.FIELD_NAMES) == _frame_kernel.FIELDS == len(set(_frame_kernel.FIELD_NAMES))
    assert _frame_kernel.FIELD_NAMES[:8] == ("strength", "x_mm", "y_mm", "major_mm", "minor_mm", "angle_deg",
                                             "area_mm2", "peak")
    from optitac_edge.core.contact import ContactEstimate

    estimate_fields = {f.name for f in dataclasses.fields(ContactEstimate)}
    assert {"strength", "x_mm", "depth_mm", "force_n", "confidence", "shape"} <= estimate_fields


def test_the_type_stub_names_what_the_module_has() -> None:
    """``_frame_kernel.pyi`` declares every public name of the built module, and nothing it lacks; each class
    the methods and attributes it has."""
    import ast

    stub = ast.parse((Path(compiled.__file__).parent / "_frame_kernel.pyi").read_text())
    declared: dict[str, set[str]] = {}
    for node in stub.body:
        if isinstance(node, ast.ClassDef):
            declared[node.name] = {n.name for n in node.body if isinstance(n, ast.FunctionDef)} | {
                n.target.id for n in node.body if isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name)}
        elif isinstance(node, ast.FunctionDef):
            declared[node.name] = set()
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            declared[node.target.id] = set()
    public = {n for n in dir(_frame_kernel) if not n.startswith("_")}
    assert set(declared) == public
    for name, members in declared.items():
        obj = getattr(_frame_kernel, name)
        if isinstance(obj, type):
            have = {n for n in dir(obj) if not n.startswith("_")}
            assert members - {"__init__"} == have, name


_FRAME_BYTES = """
import sys
import numpy as np
sys.path.insert(0, sys.argv[1])
from test_kernel import synthetic_bundle
from optitac_edge.core import _frame_kernel
from optitac_edge.core.pipeline import Pipeline

pipe = Pipeline(synthetic_bundle("gray"), compiled=True)
plan = pipe.engine.plan.as_dict()
for fmt_bytes, pixels in ((64, plan["frame_pixels"]), (64, 2_000_000_000)):
    bad = {**plan, "frame_bytes": fmt_bytes, "frame_pixels": pixels}
    try:
        k = _frame_kernel.Kernel(bad)
    except ValueError as exc:
        assert "frame_bytes" in str(exc), exc
        continue
    frame = np.zeros(fmt_bytes, dtype=np.uint8)
    k.means(frame)  # reads past a 64-byte buffer
    print("accepted")
    sys.exit(0)
print("ok")
"""


def test_a_plans_frame_size_must_hold_every_pixel_it_reads() -> None:
    """``Kernel(plan)`` trusted ``frame_bytes`` against ``frame_pixels``: a plan of 64 bytes read a whole frame
    past the buffer (and pixel indices near 2e9 with a frame_pixels to match). Refused in one line."""
    r = _run_isolated(_FRAME_BYTES, str(Path(__file__).parent))
    assert r.returncode == 0 and r.stdout.strip() == "ok", (r.returncode, r.stdout[-500:], r.stderr[-2000:])


def test_a_frame_of_the_wrong_size_is_refused(modelled) -> None:
    pipe = Pipeline(modelled, compiled=True)
    kernel = _engine(pipe).kernel
    with pytest.raises(ValueError, match="bytes"):
        kernel.means(np.zeros((10, 10), dtype=np.uint8))
    with pytest.raises(ValueError, match="bytes"):
        kernel.frame(np.zeros((480, 640), dtype=np.float32), 0, 0)


def test_without_the_kernel_the_numpy_pipeline_runs_and_says_so(modelled, monkeypatch) -> None:
    monkeypatch.setattr(compiled, "_loaded", None)
    monkeypatch.setattr(compiled, "_why_not", "not built (no module named '_frame_kernel'); pip install it where ...")
    ok, why = compiled.kernel_status()
    assert not ok and why.startswith("the numpy pipeline runs the frames: the compiled kernel is not built")
    assert not Pipeline(modelled).compiled
    with pytest.raises(ImportError, match="not built"):
        Pipeline(modelled, compiled=True)


def test_a_compiled_frame_allocates_nothing_that_outlives_it(modelled, day, traced_bytes) -> None:
    """A press held over 60 frames, run twice round: the state at the end is the state at the start."""
    pipe = Pipeline(modelled, compiled=True)
    for k, f in enumerate(day[:90]):
        pipe.process_recorded(f, k * PERIOD)
    state = {"k": 0}

    def one() -> None:
        k = state["k"] = state["k"] + 1
        pipe.process_recorded(day[30 + k % 60], (90 + k) * PERIOD)

    net, _peak = traced_bytes(one, 240)
    assert net < 200


def test_the_environment_can_ask_for_the_numpy_pipeline(modelled, monkeypatch) -> None:
    monkeypatch.setenv(compiled.ENV, "numpy")
    assert compiled.kernel_status() == (False, "the numpy pipeline runs the frames (OPTITAC_EDGE_KERNEL=numpy)")
    assert not Pipeline(modelled).compiled
    assert Pipeline(modelled, compiled=True).compiled  # asked for by the caller


def test_the_numpy_switch_is_not_a_config_override(tmp_path, monkeypatch, capsys) -> None:
    """OPTITAC_EDGE_KERNEL=numpy, documented as the switch to the numpy pipeline, broke every command that loads
    a board: 'environment OPTITAC_EDGE_KERNEL: no section 'edge''."""
    from optitac_edge.cli import main

    monkeypatch.setenv(compiled.ENV, "numpy")
    assert main(["run", "--frames", "5"]) == 0
    assert "no section" not in capsys.readouterr().err


# -- the kernel on aarch64 (qemu-user; .ci/run installs Debian's cross compiler and qemu) ---------------------


def test_the_kernel_built_for_aarch64_agrees_under_qemu(modelled, day, aarch64_tool, tmp_path, monkeypatch) -> None:
    """kernel/harness.c built with Debian's aarch64 cross compiler (NEON from the same vector code), run under
    qemu-user on the plan and frames of this machine's kernel: the same contacts, within the tolerances
    (another libm may round exp, log, atan2 in the last bit)."""
    root = Path(__file__).resolve().parents[1]
    exe = tmp_path / "harness-aarch64"
    subprocess.run(["aarch64-linux-gnu-gcc", "-std=c99", "-O3", "-ffp-contract=off", "-static", "-o", str(exe),
                    str(root / "kernel" / "harness.c"), str(root / "kernel" / "frame_kernel.c"),
                    str(root / "kernel" / "gradient_solve.c"), "-lm"], check=True)
    lines = aarch64_tool.check(Pipeline(modelled, compiled=True), day[:200], [f"qemu-aarch64 {exe}"], tmp_path,
                               "day")
    assert len(lines) == 1 and ", 0 beyond the tolerances" in lines[0], lines
    assert " 0 contacts" not in lines[0]
    monkeypatch.setattr(gradient_solve, "SOLVE_WEIGHT", 0)  # and the gradients by the sparse solve
    solved = Pipeline(modelled, compiled=True)
    assert "gs_fibers" in _engine(solved).plan.as_dict()
    lines = aarch64_tool.check(solved, day[:90], [f"qemu-aarch64 {exe}"], tmp_path, "solve")
    assert len(lines) == 1 and ", 0 beyond the tolerances" in lines[0], lines
    assert " 0 contacts" not in lines[0]


# -- memory safety: the run buffers are sized for the worst case ---------------------------------------------

_STRIPES = """
import sys
import cv2
import numpy as np
from optitac_edge.core import _frame_kernel
for h in range(1, 13):
    for w in range(1, 12):
        for phase in (0, 1):
            mask = np.zeros((h, w), dtype=np.uint8)
            mask[:, phase::2] = 1  # vertical lines: (w + 1) // 2 runs in every row, the most a row can hold
            labels = np.zeros((h, w), dtype=np.int32)
            n = _frame_kernel.label8(mask, labels)
            n_cv = cv2.connectedComponents(mask, connectivity=8)[0]
            if n != n_cv:
                sys.exit(f"{h}x{w} phase {phase}: {n} labels, OpenCV {n_cv}")
print("ok")
"""

_ODD_SIDE = """
import sys
import numpy as np
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.pipeline import Pipeline
sys.path.insert(0, sys.argv[1])
from test_kernel import synthetic_bundle, synthetic_frames
bundle = synthetic_bundle("gray", rings=2)
for n in (61, 101):
    grid = bundle.grid.__class__(n=n, x0_mm=bundle.grid.x0_mm, y0_mm=bundle.grid.y0_mm,
                                 step_mm=bundle.grid.step_mm * 60 / n)
    # a crafted operator: every other mesh column copies the mean fiber signal, the others its negative
    # (a column-striped surface: the most runs a box can hold)
    sign = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    matrix = np.repeat(np.tile(sign, n)[:, None], bundle.layout.n_fibers, axis=1) / bundle.layout.n_fibers
    crafted = CalibrationBundle(layout=bundle.layout, transform=bundle.transform, fibers=bundle.fibers, grid=grid,
                                interpolation=matrix.astype(np.float32), options=bundle.options)
    ref, kern = Pipeline(crafted, compiled=False), Pipeline(crafted, compiled=True)
    for k, frame in enumerate(synthetic_frames(bundle, 30, seed=4)):
        a, b = ref.process_recorded(frame, k * 4_166_667), kern.process_recorded(frame, k * 4_166_667)
        if a.n_contacts != b.n_contacts:
            sys.exit(f"side {n}, frame {k}: {a.n_contacts} contacts, the kernel {b.n_contacts}")
print("ok")
"""


def _run_isolated(code: str, *args: str) -> subprocess.CompletedProcess[str]:
    """``code`` in a Python of its own: a crash (a segfault, glibc's abort) is a failed test, not a dead worker."""
    import sys

    return subprocess.run([sys.executable, "-c", code, *args], check=False, capture_output=True, text=True,
                          timeout=300)


def test_the_labelling_of_striped_masks_is_opencvs() -> None:
    """Masks of vertical lines, every width from 1 to 11: a (10, 3) mask gave 7 labels for OpenCV's 3 and
    glibc aborted ("double free or corruption"), an (h, 1) mask aborted: the runs were sized h * w / 2 + 2."""
    r = _run_isolated(_STRIPES)
    assert r.returncode == 0 and r.stdout.strip() == "ok", (r.returncode, r.stdout[-500:], r.stderr[-2000:])


def test_an_odd_mesh_side_with_a_striped_surface_agrees() -> None:
    """Odd mesh sides (61, 101: a bundle may hold any side from 2 to 4096) with a column-striped surface:
    the kernel segfaulted (exit 139) where the numpy pipeline returned."""
    r = _run_isolated(_ODD_SIDE, str(Path(__file__).parent))
    assert r.returncode == 0 and r.stdout.strip() == "ok", (r.returncode, r.stdout[-500:], r.stderr[-2000:])


def test_rgb_means_read_by_the_four_pixel_chunks_are_the_samplers_to_the_bit() -> None:
    """The kernel sums an RGB fiber's grays four pixels a time from 16-byte reads; a fiber whose reads would
    pass the frame's end (here: the last 13 pixels of the frame) is read pixel by pixel. Every fiber's mean
    equals the numpy sampler's, with luma and with another colour mix, on random colours."""
    bundle = synthetic_bundle("rgb")
    t = bundle.fibers
    index = t.pixel_index.copy()
    count = int(t.pixel_start[1])
    index[:count] = np.arange(t.width * t.height - count, t.width * t.height)  # fiber 0: the frame's last pixels
    table = dataclasses.replace(t, pixel_index=index)
    rng = np.random.default_rng(4)
    for mix in ("luma", "green"):
        b = bundle.with_updates(fibers=table, options=dataclasses.replace(bundle.options, colour_mix=mix))
        kern, ref = Pipeline(b, compiled=True), Pipeline(b, compiled=False)
        assert kern.compiled
        for _ in range(5):
            frame = rng.integers(0, 256, (t.height, t.width, 3), dtype=np.uint8)
            want = ref.parts.sampler.means(frame, np.zeros(t.n_fibers, np.float32))
            kern.engine.means(frame)
            assert np.array_equal(kern.means, want), mix
