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
