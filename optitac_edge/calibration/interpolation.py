"""Build the surface operator once, at calibration: Clough-Tocher interpolation as a matrix and its factors.

The paper interpolates the baseline-subtracted fiber values onto the surface
mesh with ``scipy.interpolate.griddata(..., method="cubic")``, a Clough-Tocher
interpolant on the Delaunay triangulation of the fiber centres. For a fixed
triangulation and mesh that interpolant is linear in the data, so it is built
here, with scipy, as a matrix ``A`` (n*n, N) and its exact factorisation
``A = S @ W`` (:class:`~optitac_edge.core.surface.SurfaceFactors`), which the
runtime (:mod:`optitac_edge.core.surface`, numpy only) evaluates per frame.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from optitac_edge.core.grid import SurfaceGrid
from optitac_edge.core.layout import FiberLayout
from optitac_edge.core.surface import CELL_TERMS, SurfaceFactors

#: Relative tolerance of scipy's iterative gradient estimation used for the
#: matrix. Tighter than griddata's default (1e-6) so the matrix is the converged
#: interpolant; griddata itself then differs from it by ~1e-6 of the data range.
GRADIENT_TOL = 1e-10
GRADIENT_MAXITER = 10_000
#: Largest ``|S @ W - A|`` accepted by :func:`build_interpolation`, relative to ``max |A|``.
FACTOR_TOL = 1e-6
#: Barycentric tolerance of the second triangle search, for mesh points on the hull's
#: edges that scipy's interpolator counts as inside (its own search is that broad).
_BROAD_TOL = float(np.sqrt(np.finfo(np.float64).eps))


def _clough_tocher(xy_mm: np.ndarray, grid: SurfaceGrid) -> tuple[Any, Any, np.ndarray]:
    """scipy's Delaunay triangulation and interpolant of unit data at the fiber centres ``xy_mm`` (N, 2), and
    ``A`` in float64."""
    from scipy.interpolate import CloughTocher2DInterpolator
    from scipy.spatial import Delaunay

    n_fibers = xy_mm.shape[0]
    tri = Delaunay(np.asarray(xy_mm, dtype=np.float64))
    interp = CloughTocher2DInterpolator(
        tri, np.eye(n_fibers), fill_value=0.0, tol=GRADIENT_TOL, maxiter=GRADIENT_MAXITER
    )
    return tri, interp, np.asarray(interp(grid.points()), dtype=np.float64)


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
    return np.ascontiguousarray(_clough_tocher(np.asarray(layout.xy_mm, dtype=np.float64), grid)[2],
                                dtype=np.float32)


def build_interpolation(layout: FiberLayout, grid: SurfaceGrid) -> tuple[np.ndarray, SurfaceFactors]:
    """The interpolation matrix and its exact factorisation.

    It depends on the layout and the mesh alone, so the last one is kept: a board's sensors of one layout,
    or a fiber map rebuilt in the same process, reuse it (each caller gets its own copy of the arrays).

    ``W`` comes from the gradients scipy's interpolant estimated for unit data
    (its ``grad`` attribute, read only); the 9 weights of each mesh cell are
    solved by least squares against the rows of ``W`` of its Delaunay
    triangle's vertices (one solve per triangle).

    Parameters
    ----------
    layout : FiberLayout
        Fiber centres (N of them), mm.
    grid : SurfaceGrid
        The mesh.

    Returns
    -------
    matrix : ndarray, shape (grid.n ** 2, N), float32
        As :func:`build_interpolation_matrix`.
    factors : SurfaceFactors
        ``factors.dense()`` equals ``matrix`` to within ``FACTOR_TOL * max|matrix|``.

    Raises
    ------
    RuntimeError
        If scipy's interpolant has no gradient attribute of shape (N, N, 2), a
        mesh point inside the hull lies in no triangle, or the factors do not
        reproduce the matrix.
    """
    matrix, factors = _interpolation(np.asarray(layout.xy_mm, dtype=np.float64).tobytes(), grid)
    return matrix.copy(), SurfaceFactors(vertex_operator=factors.vertex_operator.copy(),
                                         cell_columns=factors.cell_columns.copy(),
                                         cell_weights=factors.cell_weights.copy())


@functools.lru_cache(maxsize=1)  # ~9 MB for the paper's array (100 x 100 mesh), ~41 MB for 1027 fibers
def _interpolation(xy_bytes: bytes, grid: SurfaceGrid) -> tuple[np.ndarray, SurfaceFactors]:
    """:func:`build_interpolation` of the fiber centres ``xy_bytes`` (float64, (N, 2))."""
    layout_xy = np.frombuffer(xy_bytes, dtype=np.float64).reshape(-1, 2)
    tri, interp, a64 = _clough_tocher(layout_xy, grid)
    n_fibers = layout_xy.shape[0]
    grad = getattr(interp, "grad", None)
    if not isinstance(grad, np.ndarray) or grad.shape != (n_fibers, n_fibers, 2):
        raise RuntimeError(
            "scipy's CloughTocher2DInterpolator has no gradient array 'grad' of shape "
            f"({n_fibers}, {n_fibers}, 2) (got {getattr(grad, 'shape', type(grad).__name__)}); "
            "this scipy version cannot build surface factors"
        )
    op = np.concatenate([np.eye(n_fibers), grad[:, :, 0], grad[:, :, 1]]).astype(np.float64)
    points = grid.points()
    live = np.any(a64 != 0.0, axis=1)
    simplex = np.asarray(tri.find_simplex(points), dtype=np.intp)
    missing = np.flatnonzero(live & (simplex < 0))
    if missing.size:
        simplex[missing] = tri.find_simplex(points[missing], bruteforce=True, tol=_BROAD_TOL)
    if np.any(live & (simplex < 0)):
        raise RuntimeError(f"{int(np.sum(live & (simplex < 0)))} mesh points inside the fibers' "
                           "hull lie in no Delaunay triangle")
    simplex[~live] = -1

    cols = np.zeros((a64.shape[0], CELL_TERMS), dtype=np.int32)
    wts = np.zeros((a64.shape[0], CELL_TERMS), dtype=np.float64)
    order = np.argsort(simplex, kind="stable")
    tris, starts = np.unique(simplex[order], return_index=True)
    ends = np.append(starts[1:], order.size)
    for t, a, b in zip(tris, starts, ends):
        if t < 0:
            continue
        cells = order[a:b]
        vtx = tri.simplices[t]
        terms = np.concatenate([vtx, vtx + n_fibers, vtx + 2 * n_fibers])
        sol = np.linalg.lstsq(op[terms].T, a64[cells].T, rcond=None)[0]  # (9, cells)
        cols[cells] = terms
        wts[cells] = sol.T
    factors = SurfaceFactors(
        vertex_operator=np.ascontiguousarray(op, dtype=np.float32),
        cell_columns=cols,
        cell_weights=np.ascontiguousarray(wts, dtype=np.float32),
    )
    err = float(np.abs(factors.dense().astype(np.float64) - a64).max(initial=0.0))
    scale = float(np.abs(a64).max(initial=0.0))
    if err > FACTOR_TOL * scale:
        raise RuntimeError(f"surface factors reproduce the interpolation matrix only to {err:.3g} "
                           f"(max |A| {scale:.3g}, tolerance {FACTOR_TOL:g} relative)")
    return np.ascontiguousarray(a64, dtype=np.float32), factors
