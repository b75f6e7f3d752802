"""Surface factors (A = S @ W) and the runtime surfaces: TriangleSurface, DenseSurface."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import Delaunay

import optitac_edge.calibration.interpolation as interpolation_mod
from optitac_edge.calibration.interpolation import build_interpolation, build_interpolation_matrix
from optitac_edge.core.dead_fill import dead_fill_matrix
from optitac_edge.core.grid import SurfaceGrid
from optitac_edge.core.layout import FiberLayout, hex_layout
from optitac_edge.core.surface import DenseSurface, SurfaceFactors, TriangleSurface

HEX = hex_layout()
HEX_GRID = SurfaceGrid.over_layout(HEX)


def _jittered() -> FiberLayout:
    rng = np.random.default_rng(7)
    return FiberLayout(ids=HEX.ids, xy_mm=HEX.xy_mm + rng.uniform(-0.35, 0.35, HEX.xy_mm.shape))


def _scattered() -> FiberLayout:
    xy = np.random.default_rng(11).uniform(-8.0, 8.0, (60, 2))
    return FiberLayout(ids=np.arange(60, dtype=np.int64), xy_mm=xy)


@pytest.fixture(scope="module")
def hex_built() -> tuple[np.ndarray, SurfaceFactors]:
    return build_interpolation(HEX, HEX_GRID)


def _relative_error(got: np.ndarray, ref: np.ndarray) -> float:
    return float(np.abs(np.asarray(got, np.float64) - ref).max() / np.abs(ref).max())


def test_factors_reproduce_the_matrix_hex(hex_built: tuple[np.ndarray, SurfaceFactors]) -> None:
    matrix, factors = hex_built
    n_fibers, n_cells = HEX.n_fibers, HEX_GRID.n ** 2
    assert factors.vertex_operator.shape == (3 * n_fibers, n_fibers)
    assert factors.cell_columns.shape == factors.cell_weights.shape == (n_cells, 9)
    assert factors.cell_columns.dtype == np.int32 and factors.cell_weights.dtype == np.float32
    np.testing.assert_array_equal(factors.vertex_operator[:n_fibers], np.eye(n_fibers, dtype=np.float32))
    np.testing.assert_array_equal(matrix, build_interpolation_matrix(HEX, HEX_GRID))
    assert _relative_error(factors.dense(), matrix.astype(np.float64)) <= 1e-6
    # each inside cell reads value, d/dx, d/dy of its triangle's 3 vertices; outside cells nothing
    inside = Delaunay(HEX.xy_mm).find_simplex(HEX_GRID.points()) >= 0
    assert not factors.cell_weights[~inside].any() and not factors.cell_columns[~inside].any()
    vertex = factors.cell_columns[inside] % n_fibers
    kind = factors.cell_columns[inside] // n_fibers
    np.testing.assert_array_equal(kind, np.repeat([[0, 1, 2]], 3, axis=1).repeat(inside.sum(), axis=0))
    np.testing.assert_array_equal(vertex[:, 0:3], vertex[:, 3:6])


@pytest.mark.parametrize("make_layout, n", [(_jittered, 100), (_scattered, 40)])
def test_factors_reproduce_the_matrix_irregular(make_layout, n: int) -> None:
    layout = make_layout()
    grid = SurfaceGrid.over_layout(layout, n=n)
    matrix, factors = build_interpolation(layout, grid)
    exact = build_interpolation_matrix(layout, grid).astype(np.float64)
    np.testing.assert_array_equal(matrix, exact.astype(np.float32))
    assert _relative_error(factors.dense(), exact) <= 1e-6
    surf = TriangleSurface(factors, n)
    out = np.full(n * n, np.nan, dtype=np.float32)
    v = np.random.default_rng(n).normal(0.0, 5.0, layout.n_fibers).astype(np.float32)
    assert _relative_error(surf.compute(v, out), exact @ v) <= 1e-5


def test_build_refuses_factors_that_do_not_reproduce_the_matrix(monkeypatch) -> None:
    layout = hex_layout(rings=2)
    monkeypatch.setattr(interpolation_mod, "FACTOR_TOL", 0.0)  # float32 rounding alone now fails the check
    with pytest.raises(RuntimeError, match="reproduce"):
        build_interpolation(layout, SurfaceGrid.over_layout(layout, n=20))


def test_build_refuses_an_interpolator_without_gradients(monkeypatch) -> None:
    """A scipy whose interpolant keeps no gradients in ``grad``, or in another shape."""
    from types import SimpleNamespace

    real = interpolation_mod._clough_tocher
    layout = hex_layout(rings=2)
    for grad in (None, np.zeros((layout.n_fibers, layout.n_fibers))):
        def fake(*args, grad=grad):
            tri, _, matrix = real(*args)
            return tri, SimpleNamespace(grad=grad) if grad is not None else object(), matrix

        monkeypatch.setattr(interpolation_mod, "_clough_tocher", fake)
        with pytest.raises(RuntimeError, match="grad"):
            build_interpolation(layout, SurfaceGrid.over_layout(layout, n=20))


def _signals(xy: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    out = [rng.normal(0.0, 10.0, len(xy)).astype(np.float32), np.zeros(len(xy), np.float32)]
    for _ in range(4):
        c = xy[rng.integers(len(xy))]
        bump = 60.0 * np.exp(-np.sum((xy - c) ** 2, axis=1) / (2 * 1.8 ** 2))
        out.append((bump + rng.normal(0.0, 0.5, len(xy))).astype(np.float32))
    return out


def test_triangle_surface_equals_dense_product(hex_built) -> None:
    matrix, factors = hex_built
    surf = TriangleSurface(factors, HEX_GRID.n)
    assert surf.n_triangles == 384  # 217 fibers: 6 * 8**2 triangles, at most 20 cells each
    a64 = matrix.astype(np.float64)
    out = np.full(HEX_GRID.n ** 2, np.nan, dtype=np.float32)
    for v in _signals(HEX.xy_mm, np.random.default_rng(3)):
        assert surf.compute(v, out) is out
        assert surf.evaluated == surf.n_triangles
        ref = a64 @ v
        if not ref.any():
            assert not out.any()
            continue
        assert _relative_error(out, ref) <= 1e-5


@pytest.mark.parametrize("level", [0.5, 5.0, 20.0, 59.0])
def test_triangle_surface_above_a_level_equals_the_truncated_dense_product(hex_built, level: float) -> None:
    """Cells of triangles that cannot exceed the level are skipped; after the truncation nothing differs."""
    matrix, factors = hex_built
    surf = TriangleSurface(factors, HEX_GRID.n)
    a64 = matrix.astype(np.float64)
    out = np.full(HEX_GRID.n ** 2, np.nan, dtype=np.float32)
    skipped = 0
    for v in _signals(HEX.xy_mm, np.random.default_rng(int(level))):
        surf.compute(v, out, level)
        ref = a64 @ v
        above = ref > level + 1e-4 * max(abs(level), 1.0)
        near = np.abs(ref - level) <= 1e-4 * max(abs(level), 1.0)  # float32 rounding decides these
        assert np.all(out[above] > level)
        assert np.all(out[~above & ~near] <= level)
        kept = out > level
        np.testing.assert_allclose(out[kept], ref[kept], rtol=1e-4, atol=1e-4)
        skipped += surf.n_triangles - surf.evaluated
    assert skipped > 0  # a local bump evaluates only the triangles near it


def test_patch_surface_with_dead_fiber_fill(hex_built) -> None:
    matrix, factors = hex_built
    dead = np.zeros(HEX.n_fibers, dtype=bool)
    dead[[0, 50, 51, 108, 200]] = True
    fill = dead_fill_matrix(HEX.xy_mm, dead)
    filled = matrix.astype(np.float64) @ fill
    patch = TriangleSurface(factors, HEX_GRID.n, fill=fill)
    dense = DenseSurface(matrix, fill=fill)
    out, out_dense = (np.empty(HEX_GRID.n ** 2, np.float32) for _ in range(2))
    for v in _signals(HEX.xy_mm, np.random.default_rng(5))[2:]:
        v[dead] = 1e4  # dead fibers' readings are never used
        ref = filled @ v
        assert _relative_error(patch.compute(v, out), ref) <= 1e-5
        assert _relative_error(dense.compute(v, out_dense), ref) <= 1e-5


def test_dense_surface_is_the_matrix_product(hex_built) -> None:
    matrix, _ = hex_built
    dense = DenseSurface(matrix)
    v = np.random.default_rng(2).normal(0, 1, HEX.n_fibers).astype(np.float32)
    out = np.empty(HEX_GRID.n ** 2, np.float32)
    np.testing.assert_array_equal(dense.compute(v, out), matrix @ v)
    with pytest.raises(ValueError, match="fill"):
        DenseSurface(matrix, fill=np.eye(3))


@pytest.mark.parametrize("kind, level", [("triangles", None), ("triangles", 1.0), ("dense", None)])
def test_compute_allocates_nothing(hex_built, kind: str, level: float | None, traced_bytes) -> None:
    matrix, factors = hex_built
    surf = TriangleSurface(factors, HEX_GRID.n) if kind == "triangles" else DenseSurface(matrix)
    v = np.random.default_rng(0).normal(0, 1, HEX.n_fibers).astype(np.float32)
    out = np.empty(HEX_GRID.n ** 2, np.float32)
    net, peak = traced_bytes(lambda: surf.compute(v, out, level), 100)
    assert net == 0
    # not even temporaries of array size (a (n*n,) float32 is 40 kB); with a level, the indices of
    # the triangles evaluated (8 bytes each, at most 384, and np.nonzero's own bookkeeping)
    assert peak < (1024 if level is None else 1024 + 16 * 384)


def _factors(n_fibers: int = 5, n_cells: int = 4) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {"vertex_operator": rng.random((3 * n_fibers, n_fibers), dtype=np.float32),
            "cell_columns": rng.integers(0, 3 * n_fibers, (n_cells, 9)).astype(np.int32),
            "cell_weights": rng.random((n_cells, 9), dtype=np.float32)}


def test_surface_factors_validate() -> None:
    good = SurfaceFactors(**_factors())
    assert (good.n_fibers, good.n_cells) == (5, 4)
    bad_cases = {
        "cell_columns outside": {"cell_columns": np.full((4, 9), 15, np.int32)},
        "cell_columns outside 0": {"cell_columns": np.full((4, 9), -1, np.int32)},
        "cell_columns must be": {"cell_columns": np.zeros((4, 8), np.int32)},
        "cell_columns must be (": {"cell_columns": np.zeros((4, 9), np.int64)},
        "cell_weights must be": {"cell_weights": np.zeros((3, 9), np.float32)},
        "cell_weights must": {"cell_weights": np.zeros((4, 9), np.float64)},
        "vertex_operator must be": {"vertex_operator": np.zeros((14, 5), np.float32)},
        "vertex_operator must": {"vertex_operator": np.zeros((15, 5), np.float64)},
        "2-D": {"cell_weights": np.zeros(36, np.float32)},
        "non-finite": {"cell_weights": np.full((4, 9), np.nan, np.float32)},
    }
    for message, change in bad_cases.items():
        with pytest.raises(ValueError, match=message.replace("(", r"\(")):
            SurfaceFactors(**{**_factors(), **change})


def test_patch_surface_refuses_mismatched_mesh_or_fill(hex_built) -> None:
    _, factors = hex_built
    with pytest.raises(ValueError, match="cells"):
        TriangleSurface(factors, HEX_GRID.n - 1)
    with pytest.raises(ValueError, match="fill"):
        TriangleSurface(factors, HEX_GRID.n, fill=np.eye(HEX.n_fibers - 1))


def test_patch_surface_of_hand_made_factors_with_repeated_columns() -> None:
    """Repeated columns in a cell add up (S is a sum of 9 terms), as in dense()."""
    f = _factors(n_fibers=5, n_cells=9)
    f["cell_columns"][:, 4:] = f["cell_columns"][:, :1]
    f["cell_weights"][4] = 0.0  # a cell without weights reads the permanent 0
    factors = SurfaceFactors(**f)
    v = np.random.default_rng(1).normal(0, 1, 5).astype(np.float32)
    out = np.full(9, np.nan, np.float32)
    ref = factors.dense().astype(np.float64) @ v
    np.testing.assert_allclose(TriangleSurface(factors, 3).compute(v, out), ref, rtol=1e-5, atol=1e-6)
    assert out[4] == 0.0
