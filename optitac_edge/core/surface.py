"""Fiber values -> surface, per frame: the cubic (Clough-Tocher) interpolation, dense and factored.

The paper interpolates the baseline-subtracted fiber values onto the surface
mesh with ``scipy.interpolate.griddata(..., method="cubic")``, i.e. a
Clough-Tocher interpolant on the Delaunay triangulation of the fiber centres.
For a fixed triangulation and mesh that interpolant is linear in the data
(the gradient estimate solves a linear least-curvature problem), so it is
built once, at calibration, as a matrix ``A`` of shape (n*n, N): the
surface of fiber values ``v`` is ``A @ v``. Mesh points outside the convex
hull of the fiber centres get zero rows.

``A`` also factors exactly as ``A = S @ W`` (:class:`SurfaceFactors`):
``W = [I; Gx; Gy]`` (3N, N) gives the values and the estimated gradients at
the fiber centres, and each mesh cell is a combination of only 9 entries of
``w = W @ v`` (its triangle's 3 vertices x (value, d/dx, d/dy)).
:class:`TriangleSurface` evaluates the surface that way, triangle by
triangle and only where it can exceed the truncation level (linear in the
fibers, and a contact-free frame evaluates almost none); :class:`DenseSurface`
computes the dense product for bundles without factors.

The gradient rows ``[Gx; Gy]`` of ``W`` are dense (2N, N); for large arrays the
compiled kernel finds the gradients by the sparse solve they come from instead
(:mod:`optitac_edge.core.gradient_solve`, where it is the cheaper).

The matrix and its factors are built offline, with scipy, by
:mod:`optitac_edge.calibration.interpolation`; this module, used per frame,
needs numpy only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from optitac_edge.core.gradient_solve import GradientSolve, cheaper_gradient_solve

#: Entries of ``w`` each mesh cell depends on: 3 triangle vertices x (value, d/dx, d/dy).
CELL_TERMS = 9
#: Mesh cells per chunk of :meth:`SurfaceFactors.dense` (float64 chunk of ~1.8 MB at N = 217).
_DENSE_CHUNK = 1024


@dataclass(frozen=True, eq=False)
class SurfaceFactors:
    """Exact factorisation ``A = S @ W`` of the interpolation matrix.

    Attributes
    ----------
    vertex_operator : ndarray, shape (3N, N), float32
        ``W = [I; Gx; Gy]``: ``w = W @ values`` holds the fiber values, then the
        estimated d/dx, then d/dy (per mm) at the N fiber centres.
    cell_columns : ndarray, shape (n*n, 9), int32
        For each mesh cell (row-major), the indices into ``w`` (0 ... 3N-1) it
        depends on; 0 (with weight 0) for cells outside the fibers' hull.
    cell_weights : ndarray, shape (n*n, 9), float32
        ``surface[c] = cell_weights[c] @ w[cell_columns[c]]``.

    Raises
    ------
    ValueError
        On wrong shapes or dtypes, non-finite entries or columns out of range.
    """

    vertex_operator: np.ndarray
    cell_columns: np.ndarray
    cell_weights: np.ndarray

    def __post_init__(self) -> None:
        op, cols, wts = self.vertex_operator, self.cell_columns, self.cell_weights
        for name, arr in (("vertex_operator", op), ("cell_columns", cols), ("cell_weights", wts)):
            if not isinstance(arr, np.ndarray) or arr.ndim != 2:
                raise ValueError(f"surface factors: {name} must be a 2-D array")
        if op.dtype != np.float32 or op.shape[1] < 1 or op.shape[0] != 3 * op.shape[1]:
            raise ValueError(f"surface factors: vertex_operator must be (3N, N) float32, "
                             f"got {op.shape} {op.dtype}")
        if cols.dtype != np.int32 or cols.shape[1] != CELL_TERMS:
            raise ValueError(f"surface factors: cell_columns must be (n*n, {CELL_TERMS}) int32, "
                             f"got {cols.shape} {cols.dtype}")
        if wts.dtype != np.float32 or wts.shape != cols.shape:
            raise ValueError(f"surface factors: cell_weights must be {cols.shape} float32, "
                             f"got {wts.shape} {wts.dtype}")
        if cols.size and (int(cols.min()) < 0 or int(cols.max()) >= op.shape[0]):
            raise ValueError(f"surface factors: cell_columns outside 0..{op.shape[0] - 1} "
                             f"(min {int(cols.min())}, max {int(cols.max())})")
        if not (np.isfinite(op).all() and np.isfinite(wts).all()):
            raise ValueError("surface factors: non-finite vertex_operator or cell_weights")

    @property
    def n_fibers(self) -> int:
        """N, the number of fibers."""
        return int(self.vertex_operator.shape[1])

    @property
    def n_cells(self) -> int:
        """n*n, the number of mesh cells."""
        return int(self.cell_columns.shape[0])

    def dense(self) -> np.ndarray:
        """The matrix ``S @ W``, shape (n*n, N), float32 (summed in float64, chunk by chunk)."""
        op = self.vertex_operator.astype(np.float64)
        out = np.empty((self.n_cells, self.n_fibers), dtype=np.float32)
        acc = np.empty((min(_DENSE_CHUNK, self.n_cells), self.n_fibers), dtype=np.float64)
        for a in range(0, self.n_cells, _DENSE_CHUNK):
            cols = self.cell_columns[a:a + _DENSE_CHUNK]
            wts = self.cell_weights[a:a + _DENSE_CHUNK].astype(np.float64)
            part = acc[:len(cols)]
            part.fill(0.0)
            for k in range(CELL_TERMS):
                part += wts[:, k:k + 1] * op[cols[:, k]]
            out[a:a + len(cols)] = part
        return out


def _fold_fill(operator: np.ndarray, fill: np.ndarray | None) -> np.ndarray:
    """``operator @ fill`` (float64 product) as a C-contiguous float32 array."""
    if fill is None:
        return np.ascontiguousarray(operator, dtype=np.float32)
    fill = np.asarray(fill, dtype=np.float64)
    n_fibers = operator.shape[1]
    if fill.shape != (n_fibers, n_fibers):
        raise ValueError(f"fill matrix has shape {fill.shape}, expected ({n_fibers}, {n_fibers})")
    return np.ascontiguousarray(operator.astype(np.float64) @ fill, dtype=np.float32)


class DenseSurface:
    """The surface as one dense mat-vec (bundles without :class:`SurfaceFactors`).

    Parameters
    ----------
    matrix : ndarray, shape (n*n, N)
        Interpolation matrix (``CalibrationBundle.interpolation``).
    fill : ndarray, shape (N, N), optional
        Applied to the fiber values first (dead-fiber fill, see
        :mod:`optitac_edge.core.dead_fill`); folded into the matrix once.
    """

    def __init__(self, matrix: np.ndarray, fill: np.ndarray | None = None) -> None:
        matrix = np.asarray(matrix)
        if matrix.ndim != 2:
            raise ValueError(f"interpolation matrix must be 2-D, got shape {matrix.shape}")
        self.matrix = _fold_fill(matrix, fill)
        self.n_cells, self.n_fibers = (int(s) for s in self.matrix.shape)

    def compute(self, values: np.ndarray, out: np.ndarray, level: float | None = None) -> np.ndarray:
        """``out`` (shape (n*n,), float32) = the surface of ``values`` (shape (N,), float32); ``level``
        is accepted for :class:`TriangleSurface`'s signature (the whole surface is computed)."""
        return np.matmul(self.matrix, values, out=out)

    def kernel_arrays(self) -> dict[str, np.ndarray]:
        """What the compiled kernel reads (:mod:`optitac_edge.core.compiled`): the matrix."""
        return {"dense": self.matrix}


def _by_triangle(cols: np.ndarray, wts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh cells grouped by the triangle (the 9 columns) they are evaluated from.

    Parameters
    ----------
    cols : ndarray, shape (n*n, 9), intp
        Each cell's columns of the vertex terms.
    wts : ndarray, shape (n*n, 9), float32
        Each cell's weights (all 0: a cell outside the array, never evaluated).

    Returns
    -------
    tri_cols : ndarray, shape (T, 9)
        Each triangle's columns.
    cells : ndarray, shape (max(T, 1), P), intp
        Each triangle's cells, padded with copies of its first (which write the same value twice).
    weights : ndarray, shape (max(T, 1), P, 9), float32
        Their weights.
    """
    live = np.flatnonzero(np.any(wts != 0.0, axis=1))
    tri_cols, tri_of = np.unique(cols[live], axis=0, return_inverse=True)
    tri_of = tri_of.ravel()
    order = np.argsort(tri_of, kind="stable")
    counts = np.bincount(tri_of, minlength=len(tri_cols))
    starts = np.concatenate([[0], np.cumsum(counts)])
    n_tri, width = len(tri_cols), int(counts.max(initial=1))
    cells = np.zeros((max(n_tri, 1), width), dtype=np.intp)
    weights = np.zeros((max(n_tri, 1), width, CELL_TERMS), dtype=np.float32)
    for t in range(n_tri):
        members = live[order[starts[t]:starts[t + 1]]]
        padded = np.concatenate([members, np.repeat(members[:1], width - members.size)])
        cells[t] = padded
        weights[t] = wts[padded]
    return tri_cols, cells, weights


class TriangleSurface:
    """The surface from :class:`SurfaceFactors`, triangle by triangle, only where it can exceed a level.

    Every mesh cell lies in one triangle of the fibers' triangulation and
    depends on the same 9 entries of ``w`` as every other cell of it (the 3
    vertices x (value, d/dx, d/dy)). The cells are grouped by triangle: ``T``
    triangles of at most ``P`` cells (fewer cells are padded with copies of
    the triangle's first cell, which write the same value twice), weights
    ``(T, P, 9)``.

    Given a level (the truncation level), a triangle whose bound cannot
    exceed it is not evaluated: its cells are 0. The bound of triangle ``t``
    with vertex values ``v_i`` and the 6 gradient terms ``g_j``:
    ``P_t * max_i |v_i| + sum_j M_tj |g_j|``, with ``P_t`` the largest
    ``sum_i |weight|`` of the value terms over its cells (the value weights
    sum to 1, so ``P_t`` is near 1) and ``M_tj`` the largest ``|weight|`` of
    gradient term ``j``. After the truncation (values <= level become 0) the
    surface equals the whole one exactly, and a frame costs the gradients plus
    the triangles near a contact, not the whole mesh. Without a level, every
    triangle is evaluated.
    Allocates one small array per call with a level (the indices of the triangles evaluated).

    Parameters
    ----------
    factors : SurfaceFactors
    n : int
        Mesh size (``grid.n``); ``factors.n_cells`` must be ``n * n``.
    fill : ndarray, shape (N, N), optional
        Applied to the fiber values first (dead-fiber fill); folded into the
        vertex operator once (``W @ fill``).
    fiber_xy : ndarray, shape (N, 2), optional
        The fiber centres (mm). With them the compiled kernel may find the
        gradients by a sparse solve (:mod:`optitac_edge.core.gradient_solve`)
        instead of the dense product, where that is cheaper; this class
        always computes the product.
    """

    #: The bound is compared with ``level * (1 - BOUND_MARGIN)``: float32 rounding never skips a cell above it.
    BOUND_MARGIN = 1e-4

    def __init__(self, factors: SurfaceFactors, n: int, fill: np.ndarray | None = None,
                 fiber_xy: np.ndarray | None = None) -> None:
        if factors.n_cells != n * n:
            raise ValueError(f"surface factors have {factors.n_cells} cells, expected {n * n}")
        self.n = n
        self.n_cells, self.n_fibers = n * n, factors.n_fibers
        op = _fold_fill(factors.vertex_operator, fill)
        n_f = self.n_fibers
        # the value rows of W are the identity (with a dead-fiber fill: except the dead fibers'
        # rows): w[:N] is a copy of the values plus those few rows, not an N x N product
        eye = np.eye(n_f, dtype=np.float32)
        self._value_rows = np.flatnonzero(np.any(op[:n_f] != eye, axis=1)).astype(np.intp)
        self._value_op = np.ascontiguousarray(op[self._value_rows])
        self._value_buf = np.zeros(self._value_rows.size, dtype=np.float32)
        self._grad_op = np.ascontiguousarray(op[n_f:])
        tri_cols, cells, weights = _by_triangle(factors.cell_columns, factors.cell_weights)
        #: Triangles (T) and the most cells of one (P).
        self.n_triangles = n_tri = len(tri_cols)
        self.width = width = cells.shape[1]
        self._tri_cols = np.ascontiguousarray(tri_cols, dtype=np.intp).reshape(n_tri, CELL_TERMS)
        # weights term-major per triangle, (T, 9, P): the product is a row of 9 terms times (9, P),
        # which numpy's stacked matmul does ~3x faster than (P, 9) times a column
        self._cells = cells[:n_tri]
        self._weights = np.ascontiguousarray(weights[:n_tri].transpose(0, 2, 1))
        # the bound's terms and weights term-major, (9, T): per triangle sums and maxima are vector ops
        self._cols_t = np.ascontiguousarray(self._tri_cols.T)
        # value terms first, then gradients (as calibration builds them); other factors: every term
        # is bounded by its largest weight
        nv = 3 if n_tri and bool(np.all(tri_cols[:, :3] < n_f) and np.all(tri_cols[:, 3:] >= n_f)) else 0
        self._n_value = nv
        self._value_w = np.abs(self._weights[:, :nv]).sum(axis=1).max(axis=1, initial=0.0).astype(np.float32)
        self._grad_w = np.ascontiguousarray(np.abs(self._weights[:, nv:]).max(axis=2).T, dtype=np.float32)
        self._value_bound = np.zeros(n_tri, dtype=np.float32)
        # the gradient terms summed per triangle as a (1, 6) x (6, T) product (a reduction along an
        # axis allocates); 0-d level (a scalar given to a ufunc becomes a new array every call)
        self._ones = np.ones((1, CELL_TERMS - nv), dtype=np.float32)
        self._level = np.zeros((), dtype=np.float32)
        self._all = np.arange(n_tri, dtype=np.intp)
        self._w = np.zeros(op.shape[0], dtype=np.float32)
        self._w_values, self._w_grads = self._w[:n_f], self._w[n_f:]
        self._terms_t = np.zeros((CELL_TERMS, n_tri), dtype=np.float32)
        self._bound = np.zeros(n_tri, dtype=np.float32)
        self._bound_row = self._bound.reshape(1, -1)
        self._selected = np.zeros(n_tri, dtype=bool)
        self._sel_cols = np.zeros((n_tri, CELL_TERMS), dtype=np.intp)
        self._sel_terms = np.zeros((n_tri, 1, CELL_TERMS), dtype=np.float32)
        self._sel_weights = np.zeros((n_tri, CELL_TERMS, width), dtype=np.float32)
        self._sel_cells = np.zeros((n_tri, width), dtype=np.intp)
        self._values = np.zeros((n_tri, 1, width), dtype=np.float32)
        #: Triangles evaluated by the last :meth:`compute`.
        self.evaluated = 0
        self._fiber_xy = None if fiber_xy is None else np.asarray(fiber_xy, dtype=np.float64)
        self._fill_op = op[:n_f]

    def gradient_solve(self) -> GradientSolve | None:
        """The sparse solve of the gradients when it is cheaper than the dense product and reproduces
        it (:func:`~optitac_edge.core.gradient_solve.gradient_solve`), else None (also without the
        fiber centres, or with factors whose first terms are not the triangles' vertex values)."""
        if self._fiber_xy is None or self._n_value != 3:
            return None
        return cheaper_gradient_solve(self._fiber_xy, self._tri_cols[:, :3], self._grad_op,
                                      None if self._value_rows.size == 0 else self._fill_op)

    def kernel_arrays(self) -> dict[str, np.ndarray | int]:
        """What the compiled kernel reads (:mod:`optitac_edge.core.compiled`): the operators and the
        triangles, in the layouts :meth:`compute` uses, indices as int32, and each triangle's cells
        before the padding."""
        first = self._cells[:, :1]
        counts = 1 + np.count_nonzero(self._cells[:, 1:] != first, axis=1)
        gs = self.gradient_solve()
        return {**({} if gs is None else gs.kernel_arrays()),
                "value_rows": self._value_rows.astype(np.int32), "value_op": self._value_op,
                "grad_op": self._grad_op, "n_tri": self.n_triangles, "width": self.width,
                "n_value_terms": self._n_value, "tri_cols": self._tri_cols.astype(np.int32),
                "tri_cells": self._cells.astype(np.int32), "tri_count": counts.astype(np.int32),
                "tri_weights": self._weights, "value_w": self._value_w, "grad_w": self._grad_w}

    def compute(self, values: np.ndarray, out: np.ndarray, level: float | None = None) -> np.ndarray:
        """``out`` (shape (n*n,), float32) = the surface of ``values`` (shape (N,), float32).

        With ``level``, cells of triangles that cannot exceed it are 0 (exact
        after truncation at ``level``); without, the whole surface.
        """
        np.copyto(self._w_values, values)
        if self._value_rows.size:
            np.matmul(self._value_op, values, out=self._value_buf)
            self._w_values.put(self._value_rows, self._value_buf)
        np.matmul(self._grad_op, values, out=self._w_grads)
        out.fill(0.0)
        if level is None:
            idx = self._all
        else:
            # ndarray.take, not np.take: no keyword dict per call; "wrap": the indices were checked
            # at construction (in range, so nothing wraps), "raise" would buffer ``out``
            terms_t = self._w.take(self._cols_t, out=self._terms_t, mode="wrap")
            np.abs(terms_t, out=terms_t)
            nv = self._n_value
            grads = terms_t[nv:]
            np.multiply(grads, self._grad_w, out=grads)
            np.matmul(self._ones, grads, out=self._bound_row)
            if nv:
                vb = self._value_bound
                np.maximum(terms_t[0], terms_t[1], out=vb)
                np.maximum(vb, terms_t[2], out=vb)
                np.multiply(vb, self._value_w, out=vb)
                np.add(self._bound, vb, out=self._bound)
            self._level.fill(float(level) * (1.0 - self.BOUND_MARGIN))
            np.greater(self._bound, self._level, out=self._selected)
            if not np.count_nonzero(self._selected):
                self.evaluated = 0
                return out
            idx = np.flatnonzero(self._selected)  # the one numpy buffer allocated here, 8 bytes a triangle
        k = idx.size
        self.evaluated = k
        sel_cols = self._tri_cols.take(idx, axis=0, out=self._sel_cols[:k], mode="wrap")
        self._w.take(sel_cols, out=self._sel_terms[:k, 0], mode="wrap")
        sel_weights = self._weights.take(idx, axis=0, out=self._sel_weights[:k], mode="wrap")
        vals = np.matmul(self._sel_terms[:k], sel_weights, out=self._values[:k])
        # fancy assignment, not ndarray.put: ~2.5x faster for a few thousand cells
        out[self._cells.take(idx, axis=0, out=self._sel_cells[:k], mode="wrap")] = vals[:, 0]
        return out
