"""Moments on the surface mesh: analytic cases, Hu invariance, OpenCV agreement, fast form."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from optitac_edge.core.grid import SurfaceGrid
from optitac_edge.core.layout import hex_layout
from optitac_edge.core.moments import (
    FWHM_PER_SIGMA,
    BinaryShapeMoments,
    central_moments,
    contact_ellipse,
    ellipse_from_central,
    hu_from_normalized,
    hu_moments,
    log_hu,
    log_hu_value,
    q4_from_central,
    q4_moment,
    raw_moments,
)

GRID = SurfaceGrid.over_layout(hex_layout())  # 100 x 100, ~0.242 mm cells, +-12 mm
X, Y = np.meshgrid(GRID.x_mm, GRID.y_mm)


def gaussian(x0: float, y0: float, s_major: float, s_minor: float, theta_deg: float) -> np.ndarray:
    """Sampled anisotropic Gaussian; major axis at ``theta_deg`` from +x towards +y."""
    t = math.radians(theta_deg)
    dx, dy = X - x0, Y - y0
    u = math.cos(t) * dx + math.sin(t) * dy
    v = -math.sin(t) * dx + math.cos(t) * dy
    return 50.0 * np.exp(-0.5 * ((u / s_major) ** 2 + (v / s_minor) ** 2))


def ellipse_mask(x0: float, y0: float, a: float, b: float, theta_deg: float) -> np.ndarray:
    t = math.radians(theta_deg)
    dx, dy = X - x0, Y - y0
    u = math.cos(t) * dx + math.sin(t) * dy
    v = -math.sin(t) * dx + math.cos(t) * dy
    return (u / a) ** 2 + (v / b) ** 2 <= 1.0


def polygon_mask(vertices: np.ndarray) -> np.ndarray:
    """Cells whose centre is inside a convex polygon (counter-clockwise vertices, mm)."""
    inside = np.ones(X.shape, dtype=bool)
    for (x1, y1), (x2, y2) in zip(vertices, np.roll(vertices, -1, axis=0)):
        inside &= (x2 - x1) * (Y - y1) - (y2 - y1) * (X - x1) >= 0
    return inside


def rotate(points: np.ndarray, deg: float, centre=(0.0, 0.0)) -> np.ndarray:
    t = math.radians(deg)
    r = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    return (points - centre) @ r.T + centre


# -- raw / central moments and the ellipse ------------------------------------------------


@pytest.mark.parametrize("theta", [0.0, 30.0, -60.0, 90.0, 47.5])
def test_gaussian_centroid_widths_angle(theta: float) -> None:
    x0, y0, sa, sb = 1.3, -0.7, 2.0, 1.1
    e = contact_ellipse(gaussian(x0, y0, sa, sb, theta), GRID)
    assert e.x_mm == pytest.approx(x0, abs=1e-6)
    assert e.y_mm == pytest.approx(y0, abs=1e-6)
    assert e.lambda1 == pytest.approx(sa**2, rel=1e-4)
    assert e.lambda2 == pytest.approx(sb**2, rel=1e-4)
    assert e.major_mm == pytest.approx(2.3548 * sa, rel=0.01)
    assert e.minor_mm == pytest.approx(2.3548 * sb, rel=0.01)
    assert e.major_mm == pytest.approx(FWHM_PER_SIGMA * sa, rel=1e-4)
    assert -90.0 < e.angle_deg <= 90.0
    assert e.angle_deg == pytest.approx(theta, abs=0.5)
    # strength = integral of the Gaussian = 2 pi sa sb * peak
    assert e.strength == pytest.approx(2 * math.pi * sa * sb * 50.0, rel=1e-4)


def test_rectangle_exact_discrete_variance() -> None:
    img = np.zeros((GRID.n, GRID.n))
    img[30:40, 20:61] = 3.0  # 10 rows (y) x 41 columns (x)
    e = contact_ellipse(img, GRID)
    h = GRID.step_mm
    assert e.x_mm == pytest.approx(GRID.x_mm[40], abs=1e-12)
    assert e.y_mm == pytest.approx(0.5 * (GRID.y_mm[30] + GRID.y_mm[39]), abs=1e-12)
    # variance of k equally spaced cells: (k^2 - 1) h^2 / 12
    assert e.lambda1 == pytest.approx((41**2 - 1) * h * h / 12, rel=1e-10)
    assert e.lambda2 == pytest.approx((10**2 - 1) * h * h / 12, rel=1e-10)
    assert e.angle_deg == pytest.approx(0.0, abs=1e-9)
    assert e.strength == pytest.approx(3.0 * 410 * h * h, rel=1e-12)
    e90 = contact_ellipse(img.T, GRID)  # long side along y
    assert e90.angle_deg == pytest.approx(90.0, abs=1e-9)


def test_uniform_disc() -> None:
    r = 4.0
    e = contact_ellipse(ellipse_mask(-2.0, 1.5, r, r, 0.0).astype(float), GRID)
    assert e.x_mm == pytest.approx(-2.0, abs=0.01)
    assert e.y_mm == pytest.approx(1.5, abs=0.01)
    # continuous disc: variance r^2 / 4 along every axis
    assert e.lambda1 == pytest.approx(r * r / 4, rel=0.02)
    assert e.lambda2 == pytest.approx(r * r / 4, rel=0.02)
    assert e.strength == pytest.approx(math.pi * r * r, rel=0.01)


def test_empty_surface_gives_nan_geometry() -> None:
    e = contact_ellipse(np.zeros((GRID.n, GRID.n)), GRID)
    assert e.strength == 0.0 and math.isnan(e.x_mm) and math.isnan(e.major_mm)
    assert np.all(np.isnan(hu_moments(np.zeros((GRID.n, GRID.n), bool), GRID)))


def test_raw_and_central_definitions() -> None:
    rng = np.random.default_rng(1)
    img = rng.random((GRID.n, GRID.n))
    m = raw_moments(img, GRID, order=3)
    dA = GRID.cell_area_mm2
    for p in range(4):
        for q in range(4):
            assert m[p, q] == pytest.approx(np.sum(X**p * Y**q * img) * dA, rel=1e-10, abs=1e-9)
    mu = central_moments(img, GRID, order=3)
    cx, cy = m[1, 0] / m[0, 0], m[0, 1] / m[0, 0]
    for p in range(4):
        for q in range(4):
            ref = np.sum((X - cx) ** p * (Y - cy) ** q * img) * dA
            assert mu[p, q] == pytest.approx(ref, rel=1e-9, abs=1e-9)
    assert abs(mu[1, 0]) < 1e-9 and abs(mu[0, 1]) < 1e-9


# -- Hu invariants ----------------------------------------------------------------------


def _shapes() -> dict[str, np.ndarray]:
    tri = np.array([[-3.0, -2.0], [4.0, -1.0], [0.0, 4.0]])
    return {
        "ellipse": ellipse_mask(0.5, -1.0, 5.0, 2.0, 25.0),
        "triangle": polygon_mask(tri),
        "rectangle": polygon_mask(np.array([[-4, -1.5], [4, -1.5], [4, 1.5], [-4, 1.5]], float)),
    }


@pytest.mark.parametrize("name", ["ellipse", "triangle", "rectangle"])
def test_hu_matches_opencv(name: str) -> None:
    cv2 = pytest.importorskip("cv2")
    mask = _shapes()[name]
    ref = cv2.HuMoments(cv2.moments(mask.astype(np.uint8), binaryImage=True)).ravel()
    np.testing.assert_allclose(hu_moments(mask, GRID), ref, rtol=1e-6, atol=1e-14)
    if name != "rectangle":  # symmetric: h3..h7 are 0 (OpenCV) vs ~1e-33 noise (log unstable)
        np.testing.assert_allclose(log_hu(hu_moments(mask, GRID)), log_hu(ref), rtol=1e-6)


@pytest.mark.parametrize("name", ["ellipse", "triangle", "rectangle"])
def test_hu_translation_and_right_angle_rotation_exact(name: str) -> None:
    mask = _shapes()[name]
    h = hu_moments(mask, GRID)
    shifted = np.roll(np.roll(mask, 7, axis=0), -5, axis=1)
    assert shifted.sum() == mask.sum()  # nothing wrapped
    np.testing.assert_allclose(hu_moments(shifted, GRID), h, rtol=1e-9, atol=1e-15)
    for k in (1, 2, 3):
        np.testing.assert_allclose(hu_moments(np.rot90(mask, k), GRID), h, rtol=1e-9, atol=1e-15)
    # a mirror image flips the sign of h7 only
    hm = hu_moments(mask[:, ::-1], GRID)
    np.testing.assert_allclose(hm[:6], h[:6], rtol=1e-9, atol=1e-15)
    assert hm[6] == pytest.approx(-h[6], rel=1e-9, abs=1e-15)


def test_hu_arbitrary_rotation_and_scale_approximate() -> None:
    # h1..h4 only: h5, h6 of this triangle are near 0 and change sign with rasterisation
    tri = 1.4 * np.array([[-3.0, -2.0], [4.0, -1.0], [0.0, 4.0]])  # ~40 cells across
    ref = log_hu(hu_moments(polygon_mask(tri), GRID))
    for deg in (17.0, 41.0, 133.0):
        got = log_hu(hu_moments(polygon_mask(rotate(tri, deg, centre=(0.3, 0.1))), GRID))
        np.testing.assert_allclose(got[:4], ref[:4], rtol=0.04)
    for s in (0.6, 0.8):
        got = log_hu(hu_moments(polygon_mask(tri * s), GRID))
        np.testing.assert_allclose(got[:4], ref[:4], rtol=0.04)
    # ellipses of different size: h1 = (a^2 + b^2) / (4 pi a b) for a continuous ellipse
    for scale in (0.8, 1.5, 3.0):
        h = hu_moments(ellipse_mask(0.0, 0.0, 2.5 * scale, 1.25 * scale, 10.0), GRID)
        assert h[0] == pytest.approx((2.5**2 + 1.25**2) / (4 * math.pi * 2.5 * 1.25), rel=0.03)


def test_log_hu_sign_zero_nan() -> None:
    h = np.array([1e-3, -1e-5, 0.0, np.nan, 1.0, -1.0, 10.0])
    out = log_hu(h)
    np.testing.assert_allclose(out[[0, 1, 2, 4, 5, 6]], [3.0, -5.0, 0.0, 0.0, 0.0, -1.0])
    assert math.isnan(out[3])
    buf = h.copy()
    assert log_hu(buf, out=buf) is buf


# -- q4: the 4-fold symmetry magnitude |c40| / mu00**3 ------------------------------------

FINE = SurfaceGrid(n=1201, x0_mm=-12.0, y0_mm=-12.0, step_mm=0.02)  # 0.02 mm cells
FX, FY = np.meshgrid(FINE.x_mm, FINE.y_mm)


def fine_rect(w: float, h: float, deg: float = 0.0, centre=(0.01, 0.01)) -> np.ndarray:
    """A w x h rectangle; centred half a cell off the grid so that it is exactly w x h when aligned."""
    t = math.radians(deg)
    dx, dy = FX - centre[0], FY - centre[1]
    u = math.cos(t) * dx + math.sin(t) * dy
    v = -math.sin(t) * dx + math.cos(t) * dy
    return (np.abs(u) <= w / 2) & (np.abs(v) <= h / 2)


def test_q4_analytic_moments() -> None:
    a = 3.7
    mu = np.zeros((5, 5))
    mu[0, 0] = a**2
    mu[2, 0] = mu[0, 2] = a**4 / 12
    mu[4, 0] = mu[0, 4] = a**6 / 80
    mu[2, 2] = a**6 / 144
    assert q4_from_central(mu) == pytest.approx(1.0 / 60.0, rel=1e-12)
    # a square rotated by t: c40 -> c40 * exp(4it); the moments of a square at 22.5 degrees
    # have mu40 - 6 mu22 + mu04 = 0 and mu31 - mu13 = +-a^6/240 (|c40| unchanged)
    mu_r = np.zeros((5, 5))
    mu_r[0, 0] = a**2
    mu_r[3, 1], mu_r[1, 3] = a**6 / 480, -a**6 / 480
    assert q4_from_central(mu_r) == pytest.approx(1.0 / 60.0, rel=1e-12)
    # an r : 1 rectangle
    w, h = 2.0 * a, a
    mu_rect = np.zeros((5, 5))
    mu_rect[0, 0] = w * h
    mu_rect[4, 0], mu_rect[0, 4] = w**5 * h / 80, w * h**5 / 80
    mu_rect[2, 2] = w**3 * h**3 / 144
    assert q4_from_central(mu_rect) == pytest.approx(abs((4 + 1 / 4) / 80 - 1 / 24), rel=1e-12)
    assert math.isnan(q4_from_central(np.zeros((5, 5))))


def test_q4_of_disc_square_rectangle_on_a_fine_grid() -> None:
    disc = np.hypot(FX - 0.7, FY + 1.3) <= 4.0
    assert q4_moment(disc, FINE) < 1e-4  # 1/60 for a square
    assert q4_moment(fine_rect(6.0, 6.0, centre=(1.11, -0.39)), FINE) == pytest.approx(1 / 60, rel=2e-3)
    assert q4_moment(fine_rect(8.0, 4.0), FINE) == pytest.approx((4 + 1 / 4) / 80 - 1 / 24, rel=2e-3)
    assert q4_moment(np.zeros_like(disc), FINE) != q4_moment(np.zeros_like(disc), FINE)  # NaN


@pytest.mark.parametrize("deg", [0.0, 10.0, 22.5, 37.0, 45.0, 71.0])
def test_q4_is_rotation_and_scale_invariant(deg: float) -> None:
    for side in (3.0, 6.0, 12.0):
        assert q4_moment(fine_rect(side, side, deg), FINE) == pytest.approx(1 / 60, rel=0.01), side
    ratio = (9 + 1 / 9) / 80 - 1 / 24
    assert q4_moment(fine_rect(9.0, 3.0, deg, centre=(-1.01, 2.01)), FINE) == pytest.approx(ratio, rel=0.01)
    # an equilateral triangle (3-fold symmetry) has c40 = 0
    tri = rotate(np.array([[0.0, 4.0], [-3.4641, -2.0], [3.4641, -2.0]]), deg)
    inside = np.ones(FX.shape, dtype=bool)
    for (x1, y1), (x2, y2) in zip(tri, np.roll(tri, -1, axis=0)):
        inside &= (x2 - x1) * (FY - y1) - (y2 - y1) * (FX - x1) >= 0
    assert q4_moment(inside, FINE) < 2e-4


def test_q4_on_the_runtime_mesh_separates_disc_and_square() -> None:
    for x0, y0 in ((0.0, 0.0), (3.3, -2.1)):
        disc = (X - x0) ** 2 + (Y - y0) ** 2 <= 3.0**2
        square = polygon_mask(rotate(np.array([[-2.6, -2.6], [2.6, -2.6], [2.6, 2.6], [-2.6, 2.6]]),
                                     17.0) + (x0, y0))
        assert q4_moment(disc, GRID) < 3e-3
        assert q4_moment(square, GRID) == pytest.approx(1 / 60, rel=0.1)


# -- the fast form ------------------------------------------------------------------------


def _box(mask: np.ndarray) -> tuple[np.ndarray, int, int]:
    """The mask's bounding box (float32 0/1) and its first column / row, as the pipeline reads it."""
    rows, cols = np.nonzero(mask)
    r0, c0 = int(rows.min()), int(cols.min())
    return mask[r0:rows.max() + 1, c0:cols.max() + 1].astype(np.float32), c0, r0


def test_opencv_moments_of_a_box_give_the_ellipse_in_mm() -> None:
    """The pipeline's form: cv2.moments of the bounding box, cells -> mm, equals contact_ellipse."""
    surface = (gaussian(5.0, -3.0, 2.5, 0.8, 70.0) + 3.0 * gaussian(-4, 6, 1.0, 1.0, 0.0))
    surface = np.where(surface > 2.0, surface, 0.0).astype(np.float32)
    box, c0, r0 = _box(surface > 0)
    img = surface[r0:r0 + box.shape[0], c0:c0 + box.shape[1]]
    m = cv2.moments(img)
    step, area = GRID.step_mm, GRID.cell_area_mm2
    e = ellipse_from_central(m["m00"] * area, GRID.x0_mm + step * (c0 + m["m10"] / m["m00"]),
                             GRID.y0_mm + step * (r0 + m["m01"] / m["m00"]), m["mu20"] * step ** 2 * area,
                             m["mu11"] * step ** 2 * area, m["mu02"] * step ** 2 * area)
    np.testing.assert_allclose(e, contact_ellipse(surface, GRID), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("name", ["ellipse", "triangle", "rectangle"])
def test_hu_from_opencv_nu_equals_the_array_form_and_log_hu_numpys(name: str) -> None:
    mask = _shapes()[name]
    box, _, _ = _box(mask)
    m = cv2.moments(box)
    hu = hu_from_normalized(m["nu20"], m["nu11"], m["nu02"], m["nu30"], m["nu21"], m["nu12"], m["nu03"])
    ref = hu_moments(mask, GRID)
    np.testing.assert_allclose(hu, ref, rtol=1e-8, atol=1e-14)
    # the log scaling against numpy's, computed independently
    np.testing.assert_allclose(log_hu(ref), -np.sign(ref) * np.log10(np.abs(ref)), rtol=1e-15)


def test_log_hu_value_sign_zero_nan() -> None:
    assert log_hu_value(1e-3) == pytest.approx(3.0)
    assert log_hu_value(-1e-3) == pytest.approx(-3.0)
    assert log_hu_value(0.0) == 0.0
    assert math.isnan(log_hu_value(math.nan))


def _surface_box(mask: np.ndarray, seed: int) -> tuple[np.ndarray, float]:
    """A float32 bounding box of noisy values, above ``level`` exactly on ``mask``."""
    box, c0, r0 = _box(mask)
    inside = mask[r0:r0 + box.shape[0], c0:c0 + box.shape[1]]
    values = np.random.default_rng(seed).uniform(0.0, 10.0, box.shape).astype(np.float32)
    return np.where(inside, values + np.float32(3.0), values * np.float32(0.25)).astype(np.float32), 2.75


@pytest.mark.parametrize("name", ["ellipse", "triangle", "rectangle"])
def test_binary_shape_moments_raw_equal_opencv_and_the_explicit_sums(name: str) -> None:
    mask = _shapes()[name]
    img, level = _surface_box(mask, 1)
    raw = BinaryShapeMoments(GRID.n).raw(img, level)
    binary = (img > level).astype(np.float64)
    y, x = np.mgrid[:img.shape[0], :img.shape[1]].astype(np.float64)
    for q in range(5):
        for p in range(5 - q):
            assert raw[q, p] == np.sum(binary * x ** p * y ** q)  # exact: integers in float64
    m = cv2.moments((img > level).astype(np.float32))
    assert (raw[0, 0], raw[0, 1], raw[1, 0], raw[1, 1], raw[0, 3]) == pytest.approx(
        (m["m00"], m["m10"], m["m01"], m["m11"], m["m30"]), rel=1e-12)


@pytest.mark.parametrize("x0, y0, deg", [(0.0, 0.0, 33.0), (-7.5, 6.0, 10.0), (8.0, 8.0, 71.0)])
def test_binary_shape_moments_hu_and_q4_equal_the_array_forms(x0: float, y0: float, deg: float) -> None:
    """Far from the box origin too (raw -> central cancellation), rectangles and a triangle."""
    shapes = BinaryShapeMoments(GRID.n)
    rect = polygon_mask(rotate(np.array([[-2.0, -1.5], [2.0, -1.5], [2.0, 1.5], [-2.0, 1.5]]), deg) + (x0, y0))
    tri = polygon_mask(rotate(np.array([[-3.0, -2.0], [3.0, -2.0], [0.0, 3.0]]), deg) + (x0, y0))
    for seed, mask in enumerate((rect, tri, ellipse_mask(x0, y0, 3.0, 1.2, deg))):
        img, level = _surface_box(mask, seed)
        got = shapes.hu_q4(img, level)
        assert got is not None
        hu, q4 = got
        np.testing.assert_allclose(hu, hu_moments(mask, GRID), rtol=1e-8, atol=1e-14)
        assert q4 == pytest.approx(q4_moment(mask, GRID), rel=1e-9, abs=1e-15)
    square, level = _surface_box(polygon_mask(np.array([[-3.0, -3.0], [3.0, -3.0], [3.0, 3.0], [-3.0, 3.0]])), 5)
    got = shapes.hu_q4(square, level)
    assert got is not None and got[1] == pytest.approx(1 / 60, rel=0.05)


def test_binary_shape_moments_of_nothing_above_the_level_is_none() -> None:
    shapes = BinaryShapeMoments(GRID.n)
    img = np.full((7, 5), 2.0, np.float32)
    assert shapes.hu_q4(img, 2.0) is None  # strictly above, as cv2.THRESH_BINARY
    img[3, 2] = np.nextafter(np.float32(2.0), np.float32(3.0))
    got = shapes.hu_q4(img, 2.0)
    assert got is not None and got[0][0] == 0.0 and got[1] == 0.0  # one cell: no spread


def test_binary_shape_moments_allocate_nothing_that_outlives_a_call(traced_bytes) -> None:
    shapes = BinaryShapeMoments(GRID.n)
    img, level = _surface_box(polygon_mask(np.array([[-3.0, -2.0], [3.0, -2.0], [0.0, 3.0]])), 3)
    net, _ = traced_bytes(lambda: shapes.hu_q4(img, level), 200)
    assert net < 200  # < 1 byte per call: nothing kept
