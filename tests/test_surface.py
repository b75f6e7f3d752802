"""The Clough-Tocher interpolation matrix against scipy's griddata."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import griddata
from scipy.spatial import Delaunay

from optitac_edge.calibration.interpolation import build_interpolation_matrix
from optitac_edge.core.grid import SurfaceGrid
from optitac_edge.core.layout import hex_layout
from optitac_edge.core.surface import DenseSurface

LAYOUT = hex_layout()
GRID = SurfaceGrid.over_layout(LAYOUT)
POINTS = GRID.points()
INSIDE = Delaunay(LAYOUT.xy_mm).find_simplex(POINTS) >= 0


@pytest.fixture(scope="module")
def matrix() -> np.ndarray:
    return build_interpolation_matrix(LAYOUT, GRID)


def _griddata(values: np.ndarray) -> np.ndarray:
    return griddata(LAYOUT.xy_mm, values, (POINTS[:, 0], POINTS[:, 1]), method="cubic", fill_value=0.0)


def test_shape_dtype(matrix: np.ndarray) -> None:
    assert matrix.shape == (GRID.n**2, LAYOUT.n_fibers)
    assert matrix.dtype == np.float32 and matrix.flags.c_contiguous
    assert 0.3 < INSIDE.mean() < 0.9  # the hexagon covers part of the square mesh


def test_unit_vectors_match_griddata(matrix: np.ndarray) -> None:
    for k in (0, 50, 108, 216):
        e = np.zeros(LAYOUT.n_fibers)
        e[k] = 1.0
        np.testing.assert_allclose(matrix[:, k], _griddata(e), atol=2e-5)


def test_random_and_realistic_values_match_griddata(matrix: np.ndarray) -> None:
    rng = np.random.default_rng(3)
    out = np.empty(GRID.n**2, dtype=np.float32)
    dense = DenseSurface(matrix)
    xy = LAYOUT.xy_mm
    for _ in range(4):
        c = rng.uniform(-7, 7, 2)
        v = -60.0 * np.exp(-((xy - c) ** 2).sum(1) / (2 * 1.8**2)) + rng.normal(0, 1.0, len(xy))
        v = v.astype(np.float32)
        surf = dense.compute(v, out)
        assert surf is out
        ref = _griddata(v.astype(np.float64))
        assert np.abs(surf - ref).max() < 1e-3  # gray levels; values span ~60
    v = rng.normal(0, 10.0, len(xy)).astype(np.float32)
    assert np.abs(dense.compute(v, out) - _griddata(v.astype(np.float64))).max() < 1e-3


def test_constant_and_linear_reproduced_inside_hull(matrix: np.ndarray) -> None:
    m = matrix.astype(np.float64)
    x, y = LAYOUT.xy_mm[:, 0], LAYOUT.xy_mm[:, 1]
    np.testing.assert_allclose((m @ np.full(len(x), 7.0))[INSIDE], 7.0, atol=1e-4)
    lin = 3.0 - 2.0 * x + 0.5 * y
    expect = 3.0 - 2.0 * POINTS[:, 0] + 0.5 * POINTS[:, 1]
    np.testing.assert_allclose((m @ lin)[INSIDE], expect[INSIDE], atol=1e-4)


def test_zero_outside_hull(matrix: np.ndarray) -> None:
    assert not np.any(matrix[~INSIDE])
    assert np.all(np.abs(matrix[INSIDE]).sum(axis=1) > 0)


def test_a_kept_surface_operator_is_handed_out_as_a_copy():
    """build_interpolation keeps the last operator (it depends on the layout and mesh alone): a caller that
    changes what it got does not change what the next caller gets, and another layout gets its own."""
    from optitac_edge.calibration.interpolation import build_interpolation

    layout = hex_layout(3)
    grid = SurfaceGrid.for_layout(layout)
    matrix, factors = build_interpolation(layout, grid)
    kept = matrix.copy(), factors.vertex_operator.copy(), factors.cell_weights.copy()
    matrix[:] = 7.0
    factors.vertex_operator[:] = 7.0
    factors.cell_weights[:] = 7.0
    again, factors_again = build_interpolation(layout, grid)
    assert np.array_equal(again, kept[0]) and np.array_equal(factors_again.vertex_operator, kept[1])
    assert np.array_equal(factors_again.cell_weights, kept[2])
    other = hex_layout(3, pitch_mm=2.0)
    assert not np.array_equal(build_interpolation(other, SurfaceGrid.for_layout(other))[0], kept[0])
