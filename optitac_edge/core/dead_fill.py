"""Dead-fiber fill: each dead fiber takes the mean of its neighbours, as one linear map.

The fill is linear in the fiber values, so it is a matrix ``F`` (N x N):
``filled = F @ values`` with ``F`` the identity on live fibers and, for dead
fibers, the harmonic fill (each dead fiber equals the mean of its neighbours,
live or dead, solved jointly so clusters of dead fibers are filled too). The
pipeline folds it into the interpolation matrix once (``A' = A @ F``): no
per-frame cost, and the dead fibers' own values are never read (their columns
of ``A'`` are zero). numpy only.
"""

from __future__ import annotations

import numpy as np

#: Fibers closer than this many times a fiber's nearest-neighbour distance are its neighbours.
NEIGHBOUR_FACTOR = 1.3


def neighbour_matrix(xy_mm: np.ndarray, factor: float = NEIGHBOUR_FACTOR) -> np.ndarray:
    """Adjacency, shape (N, N), bool: ``j`` is a neighbour of ``i`` (never ``i`` itself).

    ``j`` is a neighbour of ``i`` if their distance is at most ``factor`` times
    ``i``'s nearest-neighbour distance (the six ring neighbours on a hexagonal array).
    """
    xy = np.asarray(xy_mm, dtype=np.float64)
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    np.fill_diagonal(d, np.inf)
    nearest = d.min(axis=1)
    return d <= factor * nearest[:, None]


def dead_fill_matrix(xy_mm: np.ndarray, dead: np.ndarray) -> np.ndarray:
    """The fill map ``F``, shape (N, N), float64 (see the module docstring).

    Parameters
    ----------
    xy_mm : ndarray, shape (N, 2)
        Fiber centres, mm.
    dead : ndarray, shape (N,), bool

    Returns
    -------
    ndarray
        ``F[:, dead] == 0``; rows of live fibers are unit rows; each dead row
        sums to 1 (if the dead fiber is connected to a live one through
        neighbours; an isolated all-dead cluster gets 0).
    """
    dead = np.asarray(dead, dtype=bool)
    n = dead.size
    f = np.eye(n, dtype=np.float64)
    if not dead.any():
        return f
    f[:, dead] = 0.0
    adj = neighbour_matrix(xy_mm).astype(np.float64)
    d_idx, l_idx = np.flatnonzero(dead), np.flatnonzero(~dead)
    w = adj[d_idx] / np.maximum(adj[d_idx].sum(axis=1, keepdims=True), 1.0)
    system = np.eye(d_idx.size) - w[:, d_idx]
    rhs = w[:, l_idx]
    sol = np.linalg.lstsq(system, rhs, rcond=None)[0]
    sol[np.abs(sol) < 1e-12] = 0.0
    f[np.ix_(d_idx, l_idx)] = sol
    f[np.ix_(d_idx, d_idx)] = 0.0
    return f
