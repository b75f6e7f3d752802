"""TiledSurface: the truncated surface computed tile by tile equals the full mat-vec, truncated."""

from __future__ import annotations

import numpy as np
import pytest

from optitac_edge.grid import SurfaceGrid
from optitac_edge.layout import hex_layout
from optitac_edge.surface import TiledSurface, build_interpolation_matrix


@pytest.fixture(scope="module")
def matrix() -> np.ndarray:
    layout = hex_layout()
    return build_interpolation_matrix(layout, SurfaceGrid.over_layout(layout))


def _truncated(matrix: np.ndarray, values: np.ndarray, level: float) -> np.ndarray:
    full = matrix @ values
    return np.where(full > level, full, 0.0).astype(np.float32)


@pytest.mark.parametrize("tile", [1, 4, 6, 8, 13])
def test_tiled_equals_truncated_full(matrix: np.ndarray, tile: int) -> None:
    n = round(np.sqrt(matrix.shape[0]))
    rng = np.random.default_rng(tile)
    ts = TiledSurface(matrix, n, tile)
    out = np.full(n * n, np.nan, dtype=np.float32)
    xy = hex_layout().xy_mm
    for k in range(30):
        values = rng.normal(0.0, 0.002, matrix.shape[1]).astype(np.float32)  # noise
        if k % 3:  # a press: a bump of a few fibers
            c = xy[rng.integers(len(xy))]
            values += (0.3 * np.exp(-np.sum((xy - c) ** 2, axis=1) / (2 * 2.0 ** 2))).astype(np.float32)
        level = 0.008
        ts.compute(values, level, out)
        ref = _truncated(matrix, values, level)
        got = np.where(out > level, out, 0.0)
        np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-6)
        if k % 3 == 0:
            assert ts.tiles_computed < ts.n_tiles  # noise alone: most tiles skipped


def test_no_values_no_tiles(matrix: np.ndarray) -> None:
    n = round(np.sqrt(matrix.shape[0]))
    ts = TiledSurface(matrix, n)
    out = np.ones(n * n, dtype=np.float32)
    ts.compute(np.zeros(matrix.shape[1], np.float32), 0.0, out)
    assert ts.tiles_computed == 0 and not out.any()
