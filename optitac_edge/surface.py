"""Fiber values -> surface: cubic (Clough-Tocher) interpolation as one matrix.

The paper interpolates the baseline-subtracted fiber values onto the surface
mesh with ``scipy.interpolate.griddata(..., method="cubic")``, i.e. a
Clough-Tocher interpolant on the Delaunay triangulation of the fiber centres.
For a fixed triangulation and mesh that interpolant is linear in the data
(the gradient estimate solves a linear least-curvature problem), so it is
computed once, at calibration, as a matrix ``A`` of shape (n*n, N): the
surface of fiber values ``v`` is ``A @ v``. Mesh points outside the convex
hull of the fiber centres get zero rows.

``scipy`` is imported only inside :func:`build_interpolation_matrix`; the
runtime function :func:`surface_from_fibers` needs numpy only.
"""

from __future__ import annotations

import numpy as np

from .grid import SurfaceGrid
from .layout import FiberLayout

#: Relative tolerance of scipy's iterative gradient estimation used for the
#: matrix. Tighter than griddata's default (1e-6) so the matrix is the converged
#: interpolant; griddata itself then differs from it by ~1e-6 of the data range.
GRADIENT_TOL = 1e-10
GRADIENT_MAXITER = 10_000


def build_interpolation_matrix(layout: FiberLayout, grid: SurfaceGrid) -> np.ndarray:
    """Clough-Tocher interpolation from fiber centres onto the surface mesh.

    Parameters
    ----------
    layout : FiberLayout
        Fiber centres (N of them), mm.
    grid : SurfaceGrid
        The mesh, ``grid.n`` x ``grid.n`` points, row-major (see
        :meth:`SurfaceGrid.points`).

    Returns
    -------
    ndarray, shape (grid.n ** 2, N), float32
        ``matrix @ values`` equals
        ``griddata(layout.xy_mm, values, grid.points(), method="cubic",
        fill_value=0)`` up to the convergence tolerance of griddata's gradient
        estimate (~1e-6 relative). Rows of mesh points outside the convex hull
        of the fiber centres are zero.
    """
    from scipy.interpolate import CloughTocher2DInterpolator
    from scipy.spatial import Delaunay

    n_fibers = layout.n_fibers
    tri = Delaunay(np.asarray(layout.xy_mm, dtype=np.float64))
    interp = CloughTocher2DInterpolator(
        tri, np.eye(n_fibers), fill_value=0.0, tol=GRADIENT_TOL, maxiter=GRADIENT_MAXITER
    )
    matrix = interp(grid.points())
    return np.ascontiguousarray(matrix, dtype=np.float32)


def surface_from_fibers(matrix: np.ndarray, values: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Interpolate fiber values onto the mesh: ``out = matrix @ values``.

    Parameters
    ----------
    matrix : ndarray, shape (n*n, N), float32
        From :func:`build_interpolation_matrix` (``CalibrationBundle.interpolation``).
    values : ndarray, shape (N,), float32
        Fiber values (e.g. baseline-subtracted gray levels).
    out : ndarray, shape (n*n,), float32
        Receives the surface in row-major mesh order; reshape to (n, n) for
        ``surface[row, col]`` = value at ``(x_mm[col], y_mm[row])``.

    Returns
    -------
    ndarray
        ``out``.
    """
    return np.matmul(matrix, values, out=out)


class TiledSurface:
    """``matrix @ values`` truncated at a level, computed only on tiles that can exceed it.

    The mesh is cut into square tiles of ``tile`` x ``tile`` cells. For each tile
    ``t`` and fiber ``j``, ``bound[t, j]`` is the largest ``|matrix[c, j]|`` over
    the tile's cells ``c``, so ``|surface[c]| <= bound[t] @ |values|`` for every
    cell of the tile. Tiles whose bound is at or below the truncation level are
    entirely truncated to 0 and are not computed; the others are computed
    exactly (their matrix rows are stored tile by tile, contiguous, and runs of
    consecutive active tiles are one mat-vec each). The result equals
    ``where(matrix @ values > level, matrix @ values, 0)`` up to float32 rounding
    of the row dot products. Rows of mesh points outside the fibers' hull
    (all-zero rows) are dropped.

    Parameters
    ----------
    matrix : ndarray, shape (n*n, N), float32
    n : int
        Mesh size (``grid.n``).
    tile : int
        Tile side, cells.
    """

    #: Inactive tiles between two active ones that are computed rather than split into two calls.
    merge_gap = 4

    def __init__(self, matrix: np.ndarray, n: int, tile: int = 6) -> None:
        matrix = np.asarray(matrix, dtype=np.float32)
        n_cells, n_fibers = matrix.shape
        if n_cells != n * n:
            raise ValueError(f"matrix has {n_cells} rows, expected {n * n}")
        rows, cols = np.divmod(np.arange(n_cells), n)
        tile_of = (rows // tile) * (-(-n // tile)) + cols // tile
        live = np.any(matrix != 0.0, axis=1)
        order = np.lexsort((np.arange(n_cells), tile_of))
        order = order[live[order]]
        tiles, starts = np.unique(tile_of[order], return_index=True)
        self.n_cells = n_cells
        self.n_tiles = int(tiles.size)
        #: cell index (flat, row-major) of each stored row, tile by tile
        self.cells = order.astype(np.intp)
        self.starts = np.append(starts, order.size).astype(np.intp)
        self._starts = [int(v) for v in self.starts]
        self.matrix = np.ascontiguousarray(matrix[order])
        # per tile: the mean row, and the largest deviation of a row from it, per fiber
        m64 = self.matrix.astype(np.float64)
        counts = np.diff(self.starts)[:, None]
        mean = np.add.reduceat(m64, starts, axis=0) / counts if order.size else np.zeros((0, n_fibers))
        dev = np.abs(m64 - np.repeat(mean, counts[:, 0], axis=0))
        dev = np.maximum.reduceat(dev, starts, axis=0) if order.size else mean
        # rounding margin: the float32 products of the compute and of the bound differ by < 1e-5
        dev += 1e-5 * np.abs(m64).max(initial=0.0)
        self._mean = np.ascontiguousarray(mean, dtype=np.float32)
        self._dev = np.ascontiguousarray(dev, dtype=np.float32)
        self._abs = np.zeros(n_fibers, dtype=np.float32)
        self._tile_bound = np.zeros(self.n_tiles, dtype=np.float32)
        self._tile_dev = np.zeros(self.n_tiles, dtype=np.float32)
        self._active = np.zeros(self.n_tiles, dtype=bool)
        self._buf = np.zeros(order.size, dtype=np.float32)
        #: tiles computed in the last call
        self.tiles_computed = 0

    def compute(self, values: np.ndarray, level: float, out: np.ndarray) -> np.ndarray:
        """``out`` (shape (n*n,), float32) = the surface, 0 wherever it is <= ``level``."""
        np.abs(values, out=self._abs)
        np.matmul(self._mean, values, out=self._tile_bound)
        np.matmul(self._dev, self._abs, out=self._tile_dev)
        self._tile_bound += self._tile_dev
        np.greater(self._tile_bound, np.float32(level), out=self._active)
        out.fill(0.0)
        active = np.flatnonzero(self._active)
        computed = 0
        if active.size:
            # runs of active tiles, joined across gaps of up to ``merge_gap`` tiles (computing
            # a tile that is truncated anyway costs less than another call)
            cut = np.flatnonzero(np.diff(active) > self.merge_gap + 1)
            first = [int(active[0])] + (active[cut + 1]).tolist()
            last = (active[cut]).tolist() + [int(active[-1])]
            starts, buf, cells, mat = self._starts, self._buf, self.cells, self.matrix
            for t, u in zip(first, last):
                a, b = starts[t], starts[u + 1]
                np.matmul(mat[a:b], values, out=buf[a:b])
                out.put(cells[a:b], buf[a:b])
                computed += u + 1 - t
        self.tiles_computed = computed
        return out
