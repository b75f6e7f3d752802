"""The fibers' surface gradients as a sparse solve instead of a dense (2N, N) product.

The factored surface (:mod:`optitac_edge.core.surface`) needs the estimated
d/dx and d/dy at every fiber centre, ``g = G @ v`` with ``G`` dense (2N, N):
scipy's Clough-Tocher gradient estimate couples every fiber to every other,
so the product grows with N² (2.1 M multiply-adds at 1027 fibers).

That estimate (scipy's ``estimate_gradients_2d_global``, Nielson's
minimum-curvature method) iterates, fiber by fiber over the Delaunay
neighbours ``j`` of fiber ``i`` (``e = x_j - x_i``, ``L = |e|``), to the
solution of a sparse linear system::

    sum_j 4 e e^T / L^3 g_i + sum_j 2 e e^T / L^3 g_j = sum_j 6 (v_j - v_i) e / L^3

``K g = B v``: ``K`` (2N, 2N) symmetric positive definite with a 2x2 block per
neighbour pair, ``B`` (2N, N) with 6 entries per row pair. ``K`` is well
conditioned (about 4 at 217 and 1027 fibers), so its Cholesky factor in
float32 solves it to ~2e-7 of the gradients' scale, the rounding of the
float32 ``G`` itself. With the fibers in reverse Cuthill-McKee order the
factor ``K = C C^T`` lies in a narrow envelope: each row ``p`` of ``C`` is
dense from column ``row_first[p]`` to ``p``. A frame then costs two
triangular solves over the envelope (about 2 x 135 k multiply-adds at 1027
fibers) and the right side (6 neighbours a fiber).

:func:`gradient_solve` builds it (numpy only, once per pipeline) from the
fiber centres and the triangles, and checks it against the dense operator it
replaces; the compiled kernel uses it when it is the cheaper
(:func:`solve_pays`). :func:`solve_gradients` is the same solve in numpy, for
the tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Largest ``|solve - G @ v|`` accepted, relative to ``max |G @ v|`` over the probe vectors.
CHECK_TOL = 1e-5
#: Probe vectors of the check.
CHECK_PROBES = 3
#: Largest 2N whose dense float64 ``K`` is factored (2N = 2896: 64 MB, once, at start).
MAX_DOFS = 2896
#: Rows and columns of the factor are padded with zeros to multiples of this many entries (the
#: kernel's vectors; rows may then start up to PAD positions before 0 and columns end PAD after the end).
PAD = 8
#: Multiply-adds charged per envelope row for the loop around it (both solves).
ROW_COST = 16


@dataclass(frozen=True, eq=False)
class GradientSolve:
    """``g = K^-1 B v`` with ``K = C C^T``, ``C`` lower triangular in an envelope.

    The factor's positions ``2 r`` and ``2 r + 1`` are d/dx and d/dy at fiber
    ``fibers[r]`` (the fibers in reverse Cuthill-McKee order).

    Attributes
    ----------
    fibers : ndarray, shape (N,), int32
        The fiber of each pair of positions.
    diag : ndarray, shape (2N,), float32
        ``C[p, p]``.
    col_last : ndarray, shape (2N,), int32
        One past the last row of column ``p``'s envelope (``> p``; up to ``2N + PAD``: the envelope is
        padded with zeros to multiples of :data:`PAD` entries). Both triangular solves read the factor
        by its columns (the second as dot products), so a frame reads it once.
    col_ptr : ndarray, shape (2N + 1,), int64
        ``col_env[col_ptr[p]:col_ptr[p + 1]]`` is ``C[p + 1:col_last[p], p]``.
    col_env : ndarray, float32
    nbr_ptr : ndarray, shape (N + 1,), int32
        Fiber ``i``'s neighbours are ``nbr[nbr_ptr[i]:nbr_ptr[i + 1]]``.
    nbr : ndarray, shape (E,), int32
    coef : ndarray, shape (E, 2), float32
        ``6 e / L^3`` of each (fiber, neighbour) pair: the right side of fiber
        ``i``, axis ``a``, is ``sum coef[k, a] * (v[nbr[k]] - v[i])``.
    """

    fibers: np.ndarray
    diag: np.ndarray
    col_last: np.ndarray
    col_ptr: np.ndarray
    col_env: np.ndarray
    nbr_ptr: np.ndarray
    nbr: np.ndarray
    coef: np.ndarray

    @property
    def n_fibers(self) -> int:
        """N."""
        return int(self.nbr_ptr.size - 1)

    def cost(self) -> int:
        """Multiply-adds of one solve (both triangular solves, the rows' loops and the right side)."""
        return int(2 * self.col_env.size + ROW_COST * self.diag.size + 2 * self.nbr.size)

    def kernel_arrays(self) -> dict[str, np.ndarray]:
        """What the compiled kernel reads (:mod:`optitac_edge.core.compiled`)."""
        return {"gs_fibers": self.fibers, "gs_diag": self.diag, "gs_col_last": self.col_last,
                "gs_col_ptr": self.col_ptr, "gs_col_env": self.col_env, "gs_nbr_ptr": self.nbr_ptr,
                "gs_nbr": self.nbr, "gs_coef": self.coef}


def neighbours(triangles: np.ndarray, n_fibers: int) -> tuple[np.ndarray, np.ndarray]:
    """Each fiber's neighbours along the triangles' edges, sorted.

    Parameters
    ----------
    triangles : ndarray, shape (T, 3), int
        Vertex indices of the triangles.
    n_fibers : int

    Returns
    -------
    nbr_ptr : ndarray, shape (N + 1,), int32
    nbr : ndarray, shape (E,), int32
        Fiber ``i``'s neighbours are ``nbr[nbr_ptr[i]:nbr_ptr[i + 1]]``, each edge in both directions.
    """
    t = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    a = np.concatenate([t[:, 0], t[:, 1], t[:, 2], t[:, 1], t[:, 2], t[:, 0]])
    b = np.concatenate([t[:, 1], t[:, 2], t[:, 0], t[:, 0], t[:, 1], t[:, 2]])
    pairs = np.unique(a * n_fibers + b)
    src, dst = pairs // n_fibers, pairs % n_fibers
    ptr = np.zeros(n_fibers + 1, dtype=np.int32)
    np.cumsum(np.bincount(src, minlength=n_fibers), out=ptr[1:])
    return ptr, dst.astype(np.int32)


def reverse_cuthill_mckee(nbr_ptr: np.ndarray, nbr: np.ndarray) -> np.ndarray:
    """The fibers in reverse Cuthill-McKee order (a narrow envelope), each component from a far fiber.

    Returns
    -------
    ndarray, shape (N,), intp
        A permutation of the fibers.
    """
    n = nbr_ptr.size - 1
    degree = np.diff(nbr_ptr)
    src = np.repeat(np.arange(n), degree)
    seen = np.zeros(n, dtype=bool)
    out: list[np.ndarray] = []

    def bfs(start: int, mark: np.ndarray) -> np.ndarray:
        """Cuthill-McKee from ``start``, a level at a time: each new fiber goes to the first fiber of the
        level before (in order) it neighbours, a fiber's new neighbours by degree, then number."""
        levels, level = [np.array([start])], np.array([start])
        mark[start] = True
        while level.size:
            pos = np.full(n, -1)
            pos[level] = np.arange(level.size)
            edges = np.flatnonzero(pos[src] >= 0)  # the edges leaving this level
            cand = nbr[edges]
            keep = ~mark[cand]
            cand, parent = cand[keep], pos[src[edges[keep]]]
            order = np.lexsort((cand, degree[cand], parent))
            cand = cand[order]
            cand = cand[np.sort(np.unique(cand, return_index=True)[1])]  # each fiber once, at its first parent
            mark[cand] = True
            levels.append(cand)
            level = cand
        return np.concatenate(levels)

    for start in np.argsort(degree, kind="stable"):
        if seen[start]:
            continue
        far = int(bfs(int(start), seen.copy())[-1])  # a far fiber of this component (one sweep)
        out.append(bfs(far, seen))
    return np.concatenate(out)[::-1].astype(np.intp) if out else np.zeros(0, dtype=np.intp)


def nielson_system(xy: np.ndarray, nbr_ptr: np.ndarray, nbr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``K`` (dense, float64) and the right side's coefficients of the minimum-curvature gradients.

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        Fiber centres, mm.
    nbr_ptr, nbr : ndarray
        As :func:`neighbours`.

    Returns
    -------
    K : ndarray, shape (2N, 2N), float64
        Unknown ``2 i + a`` is fiber ``i``'s d/d(x, y)[a].
    coef : ndarray, shape (E, 2), float64
        ``6 e / L^3`` per (fiber, neighbour) pair.
    """
    xy = np.asarray(xy, dtype=np.float64)
    n = xy.shape[0]
    src = np.repeat(np.arange(n), np.diff(nbr_ptr))
    e = xy[nbr] - xy[src]
    inv_l3 = 1.0 / np.hypot(e[:, 0], e[:, 1]) ** 3
    outer = e[:, :, None] * e[:, None, :] * inv_l3[:, None, None]  # (E, 2, 2)
    k = np.zeros((2 * n, 2 * n))
    for a in range(2):
        for c in range(2):
            np.add.at(k, (2 * src + a, 2 * nbr + c), 2.0 * outer[:, a, c])
            np.add.at(k, (2 * src + a, 2 * src + c), 4.0 * outer[:, a, c])
    return k, 6.0 * e * inv_l3[:, None]


def solve_gradients(gs: GradientSolve, values: np.ndarray) -> np.ndarray:
    """The gradients at the fibers, in numpy, as the compiled kernel computes them (float32).

    Parameters
    ----------
    gs : GradientSolve
    values : ndarray, shape (N,)
        The fiber values (after the dead-fiber fill).

    Returns
    -------
    ndarray, shape (2N,), float32
        d/dx at the N fibers, then d/dy (per mm): the layout of ``W``'s gradient rows.
    """
    v = np.asarray(values, dtype=np.float32)
    n = gs.n_fibers
    src = np.repeat(np.arange(n), np.diff(gs.nbr_ptr))
    rhs = np.zeros((n, 2), dtype=np.float32)
    d = v[gs.nbr] - v[src]
    for axis in range(2):
        np.add.at(rhs[:, axis], src, gs.coef[:, axis] * d)
    m = 2 * n
    y = np.zeros(m + 2 * PAD, dtype=np.float32)  # position p at y[PAD + p]
    y[PAD:PAD + m] = rhs[gs.fibers].ravel()
    for p in range(PAD, PAD + m):  # C y = rhs, column by column
        y[p] /= gs.diag[p - PAD]
        y[p + 1:PAD + gs.col_last[p - PAD]] -= y[p] * gs.col_env[gs.col_ptr[p - PAD]:gs.col_ptr[p - PAD + 1]]
    for p in range(PAD + m - 1, PAD - 1, -1):  # C^T x = y: each x from its column, a dot product with the x found
        env = gs.col_env[gs.col_ptr[p - PAD]:gs.col_ptr[p - PAD + 1]].reshape(-1, 8)
        lanes = np.zeros(8, dtype=np.float32)
        for col, known in zip(env, y[p + 1:PAD + gs.col_last[p - PAD]].reshape(-1, 8)):  # lane l: elements l mod 8
            lanes += col * known
        s = ((lanes[0] + lanes[1]) + (lanes[2] + lanes[3])) + ((lanes[4] + lanes[5]) + (lanes[6] + lanes[7]))
        y[p] = (y[p] - s) / gs.diag[p - PAD]
    g = np.empty((2, n), dtype=np.float32)
    g[:, gs.fibers] = y[PAD:PAD + m].reshape(n, 2).T
    return g.ravel()


def _envelope(c: np.ndarray) -> tuple[np.ndarray, ...]:
    """The column envelope of the lower triangular ``c`` (one past each column's last row, the offsets, the
    float32 entries), each column padded with zeros to a multiple of :data:`PAD` entries (past the end)."""
    m = c.shape[0]
    nz = c != 0.0
    np.fill_diagonal(nz, True)
    last = m - np.argmax(nz[::-1], axis=0)  # one past the last nonzero of each column
    pos = np.arange(m)
    last = (pos + 1 + -(-(last - pos - 1) // PAD) * PAD).astype(np.int32)
    c = np.pad(c, PAD)
    col_ptr = np.zeros(m + 1, dtype=np.int64)
    np.cumsum(last - np.arange(m) - 1, out=col_ptr[1:])
    col_env = np.concatenate([c[PAD + p + 1:PAD + last[p], PAD + p] for p in range(m)] + [np.zeros(0)])
    return last, col_ptr, col_env.astype(np.float32)


def gradient_solve(xy: np.ndarray, triangles: np.ndarray, grad_op: np.ndarray,
                   fill_values: np.ndarray | None = None, max_cost: int | None = None) -> GradientSolve | None:
    """The sparse solve of the gradients, checked against the dense operator it replaces.

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        Fiber centres, mm (the layout the bundle was calibrated on).
    triangles : ndarray, shape (T, 3), int
        The fibers' Delaunay triangles (every edge at least once).
    grad_op : ndarray, shape (2N, N)
        The dense gradient rows of ``W`` (folded with a dead-fiber fill, if any).
    fill_values : ndarray, shape (N, N), optional
        The dead-fiber fill the solve is applied after (``g = G @ fill @ v``): the
        check compares ``solve(fill @ v)`` with ``grad_op @ v``.
    max_cost : int, optional
        Give up (None) before factoring when the solve's :meth:`~GradientSolve.cost`,
        estimated from the envelope of ``K`` (which the factor fills), would exceed it.

    Returns
    -------
    GradientSolve or None
        None when ``K`` is too large to factor here (:data:`MAX_DOFS`), not
        positive definite, or the solve differs from ``grad_op`` by more than
        :data:`CHECK_TOL` (triangles other than scipy's, or another estimate).
    """
    xy = np.asarray(xy, dtype=np.float64)
    n = xy.shape[0]
    if 2 * n > MAX_DOFS or np.asarray(grad_op).shape != (2 * n, n):
        return None
    nbr_ptr, nbr = neighbours(triangles, n)
    if np.any(np.diff(nbr_ptr) < 2):
        return None
    fibers = reverse_cuthill_mckee(nbr_ptr, nbr)
    if max_cost is not None and _estimated_cost(fibers, nbr_ptr, nbr) > max_cost:
        return None
    k, coef = nielson_system(xy, nbr_ptr, nbr)
    order = np.stack([2 * fibers, 2 * fibers + 1], axis=1).ravel()
    k = k[np.ix_(order, order)]
    try:
        c = np.linalg.cholesky(k)
    except np.linalg.LinAlgError:
        return None
    last, col_ptr, col_env = _envelope(c)
    gs = GradientSolve(fibers=fibers.astype(np.int32), diag=np.diag(c).astype(np.float32), col_last=last,
                       col_ptr=col_ptr, col_env=col_env,
                       nbr_ptr=nbr_ptr, nbr=nbr, coef=coef.astype(np.float32))
    return gs if _reproduces(gs, grad_op, fill_values) else None


def _estimated_cost(fibers: np.ndarray, nbr_ptr: np.ndarray, nbr: np.ndarray) -> int:
    """:meth:`GradientSolve.cost` before factoring, from the envelope of ``K`` in the order ``fibers`` (the
    factor fills it; counted for its rows, the columns' being about as large, unpadded)."""
    n = fibers.size
    rank = np.empty(n, dtype=np.intp)
    rank[fibers] = np.arange(n)
    src = np.repeat(np.arange(n), np.diff(nbr_ptr))
    lowest = rank.copy()
    np.minimum.at(lowest, src, rank[nbr])
    reach = rank - lowest  # each fiber's envelope in fibers; its two rows reach 2 * reach and 2 * reach + 1
    return int(2 * (4 * reach.sum() + n) + ROW_COST * 2 * n + 2 * nbr.size)


def _reproduces(gs: GradientSolve, grad_op: np.ndarray, fill_values: np.ndarray | None) -> bool:
    """Whether ``gs`` gives ``grad_op @ v`` (within :data:`CHECK_TOL`) on :data:`CHECK_PROBES` random vectors
    (a fixed seed: the same answer every start), solving ``fill_values @ v`` when there is a fill."""
    rng = np.random.default_rng(0)
    op = np.asarray(grad_op, dtype=np.float64)
    for _ in range(CHECK_PROBES):
        v = np.asarray(rng.standard_normal(gs.n_fibers), dtype=np.float32)
        want = op @ v
        filled = v if fill_values is None else np.asarray(fill_values @ v, dtype=np.float32)
        got = solve_gradients(gs, filled)
        if not np.abs(got - want).max() <= CHECK_TOL * max(float(np.abs(want).max()), 1e-30):
            return False
    return True


#: A multiply-add of the solve costs about this many of the dense product's (scattered short rows and
#: divisions against one long vector stream; callgrind, 217 and 1027 fibers).
SOLVE_WEIGHT = 4
#: Largest dense gradient operator (2N x N float32) the kernel keeps, bytes: beyond it the solve's fewer bytes
#: win at a camera's pace whatever the instructions. A frame at 240 fps finds the operator evicted (the
#: frame's own pixels, other sensors' tables): at 217 fibers the 368 KB product made the pipeline 211 us a
#: paced frame against 61 us with the solve's 146 KB (then its factor twice, by rows and by columns; 84 KB
#: since the factor is stored once), 60 against 39 us back to back (this machine, interleaved).
DENSE_BYTES_MAX = 64 * 1024


def dense_bytes(n_fibers: int) -> int:
    """Bytes of the dense gradient operator of ``n_fibers`` fibres (2N x N float32)."""
    return 2 * n_fibers * n_fibers * 4


def solve_pays(gs: GradientSolve) -> bool:
    """Whether the kernel takes the solve: the dense operator is over :data:`DENSE_BYTES_MAX` (217 fibers:
    368 KB), or :data:`SOLVE_WEIGHT` times its :meth:`~GradientSolve.cost` is under the dense product's
    ``2 N^2`` multiply-adds (1027 fibers: 1.3 M against 2.1 M; 61: no)."""
    n = gs.n_fibers
    return dense_bytes(n) > DENSE_BYTES_MAX or SOLVE_WEIGHT * gs.cost() < 2 * n ** 2


def cheaper_gradient_solve(xy: np.ndarray, triangles: np.ndarray, grad_op: np.ndarray,
                           fill_values: np.ndarray | None = None) -> GradientSolve | None:
    """:func:`gradient_solve` where it pays (:func:`solve_pays`), else None; gives up before factoring
    when the envelope alone shows it will not (a small array's dense operator is kept)."""
    n = int(np.asarray(grad_op).shape[1])
    small = dense_bytes(n) <= DENSE_BYTES_MAX
    max_cost = 2 * n * n // SOLVE_WEIGHT if SOLVE_WEIGHT and small else None
    gs = gradient_solve(xy, triangles, grad_op, fill_values, max_cost=max_cost)
    return gs if gs is not None and solve_pays(gs) else None
