"""The surface gradients as a sparse solve (optitac_edge.core.gradient_solve): the mathematics.

The solve must reproduce scipy's Clough-Tocher gradient estimate (the dense operator the calibration
builds), be exact on linear data (the minimum-curvature estimate reproduces planes), refuse triangles
other than the operator's, and keep the envelope layout the compiled kernel reads.
"""

from __future__ import annotations

import numpy as np
import pytest

from optitac_edge.calibration.interpolation import build_interpolation
from optitac_edge.core.gradient_solve import (
    PAD,
    gradient_solve,
    neighbours,
    nielson_system,
    reverse_cuthill_mckee,
    solve_gradients,
    solve_pays,
)
from optitac_edge.core.grid import SurfaceGrid
from optitac_edge.core.layout import FiberLayout, hex_layout
from optitac_edge.core.surface import TriangleSurface


def _surface(layout: FiberLayout, n: int = 30) -> TriangleSurface:
    _matrix, factors = build_interpolation(layout, SurfaceGrid.over_layout(layout, n=n))
    return TriangleSurface(factors, n, fiber_xy=layout.xy_mm)


def _parts(layout: FiberLayout) -> tuple[np.ndarray, np.ndarray]:
    """The Delaunay triangles (as the surface's factors name them) and the dense gradient rows."""
    arrays = _surface(layout).kernel_arrays()
    return np.asarray(arrays["tri_cols"])[:, :3], np.asarray(arrays["grad_op"])


@pytest.fixture(scope="module")
def hex4() -> FiberLayout:
    return hex_layout(rings=4)


@pytest.fixture(scope="module")
def irregular() -> FiberLayout:
    """A jittered hexagonal array (a real bundle's fibers are not on a perfect lattice)."""
    base = hex_layout(rings=4)
    rng = np.random.default_rng(3)
    return FiberLayout(ids=base.ids, xy_mm=base.xy_mm + rng.uniform(-0.2, 0.2, base.xy_mm.shape))


@pytest.mark.parametrize("which", ["hex4", "irregular"])
def test_the_solve_is_scipys_gradient_estimate(which, request) -> None:
    layout = request.getfixturevalue(which)
    tris, grad_op = _parts(layout)
    gs = gradient_solve(layout.xy_mm, tris, grad_op)
    assert gs is not None
    rng = np.random.default_rng(0)
    for _ in range(5):
        v = rng.standard_normal(layout.n_fibers).astype(np.float32)
        want = grad_op.astype(np.float64) @ v
        got = solve_gradients(gs, v)
        assert np.abs(got - want).max() <= 2e-6 * np.abs(want).max()


def test_the_solve_reproduces_a_plane_exactly(irregular) -> None:
    """Linear data: every fiber's gradient is the plane's (the estimate minimises curvature, which is 0)."""
    tris, grad_op = _parts(irregular)
    gs = gradient_solve(irregular.xy_mm, tris, grad_op)
    assert gs is not None
    x, y = irregular.xy_mm[:, 0], irregular.xy_mm[:, 1]
    n = irregular.n_fibers
    for a, b in ((0.3, -0.7), (1.0, 0.0), (0.0, 2.5)):
        g = solve_gradients(gs, (a * x + b * y + 4.0).astype(np.float32))
        np.testing.assert_allclose(g[:n], a, atol=2e-5 * max(abs(a), abs(b)))
        np.testing.assert_allclose(g[n:], b, atol=2e-5 * max(abs(a), abs(b)))


def test_the_system_is_symmetric_positive_definite_and_well_conditioned(hex4) -> None:
    tris, _ = _parts(hex4)
    ptr, nbr = neighbours(tris, hex4.n_fibers)
    k, coef = nielson_system(hex4.xy_mm, ptr, nbr)
    assert np.array_equal(k, k.T)
    eig = np.linalg.eigvalsh(k)
    assert eig.min() > 0 and eig.max() / eig.min() < 10
    assert coef.shape == (nbr.size, 2)


def test_other_triangles_or_another_operator_are_refused(hex4) -> None:
    tris, grad_op = _parts(hex4)
    a, b = tris[0, 0], tris[0, 1]  # an inner edge: both its triangles dropped, another system
    keep = ~(np.isin(tris, [a]).any(axis=1) & np.isin(tris, [b]).any(axis=1))
    assert keep.sum() == len(tris) - 2
    assert gradient_solve(hex4.xy_mm, tris[keep], grad_op) is None
    alone = ~np.isin(tris, [30]).any(axis=1)  # the middle fiber with no neighbours
    assert gradient_solve(hex4.xy_mm, tris[alone], grad_op) is None
    assert gradient_solve(hex4.xy_mm, tris, grad_op * 1.01) is None  # not the operator it replaces
    assert gradient_solve(hex4.xy_mm * 1.1, tris, grad_op) is None  # another geometry


def test_a_dead_fiber_fill_is_solved_after(hex4) -> None:
    """With a fill folded into the operator (``G @ fill``), the solve of the filled values reproduces it."""
    tris, grad_op = _parts(hex4)
    n = hex4.n_fibers
    fill = np.eye(n)
    fill[5] = 0.0
    fill[5, [4, 6]] = 0.5
    folded = (grad_op.astype(np.float64) @ fill).astype(np.float32)
    assert gradient_solve(hex4.xy_mm, tris, folded) is None
    gs = gradient_solve(hex4.xy_mm, tris, folded, fill_values=fill)
    assert gs is not None
    v = np.random.default_rng(1).standard_normal(n).astype(np.float32)
    want = folded.astype(np.float64) @ v
    assert np.abs(solve_gradients(gs, (fill @ v).astype(np.float32)) - want).max() <= 2e-6 * np.abs(want).max()


def test_the_envelopes_are_padded_zeros_in_multiples_of_pad(hex4) -> None:
    tris, grad_op = _parts(hex4)
    gs = gradient_solve(hex4.xy_mm, tris, grad_op)
    assert gs is not None
    m = 2 * hex4.n_fibers
    pos = np.arange(m)
    assert np.all((gs.col_last - pos - 1) % PAD == 0) and np.all(gs.col_last <= m + PAD) and np.all(gs.col_last > pos)
    assert gs.col_ptr[-1] == gs.col_env.size
    # the column envelope holds the factor below its diagonal (which the solves' products reproduce), and
    # zeros past the last row
    c_cols = np.zeros((m + 2 * PAD, m + 2 * PAD))
    for p in range(m):
        c_cols[PAD + p + 1:PAD + gs.col_last[p], PAD + p] = gs.col_env[gs.col_ptr[p]:gs.col_ptr[p + 1]]
    assert not c_cols[PAD + m:].any()
    assert np.all(np.triu(c_cols[PAD:PAD + m, PAD:PAD + m]) == 0)
    c = c_cols[PAD:PAD + m, PAD:PAD + m] + np.diag(gs.diag.astype(np.float64))
    k, _ = nielson_system(hex4.xy_mm, *neighbours(tris, hex4.n_fibers))
    order = np.stack([2 * gs.fibers, 2 * gs.fibers + 1], axis=1).ravel()
    assert np.abs(c @ c.T - k[np.ix_(order, order)]).max() <= 1e-5 * np.abs(k).max()  # C C^T = K, float32 entries


def test_reverse_cuthill_mckee_is_a_permutation_with_a_narrow_band(hex4) -> None:
    tris, _ = _parts(hex4)
    ptr, nbr = neighbours(tris, hex4.n_fibers)
    order = reverse_cuthill_mckee(ptr, nbr)
    assert np.array_equal(np.sort(order), np.arange(hex4.n_fibers))
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    src = np.repeat(np.arange(hex4.n_fibers), np.diff(ptr))
    band = np.abs(rank[src] - rank[nbr]).max()
    assert band <= 2 * 9 + 1  # about one row of the array (9 fibers at the widest) either way


def test_the_solve_pays_only_for_many_fibers(hex4) -> None:
    tris, grad_op = _parts(hex4)
    gs = gradient_solve(hex4.xy_mm, tris, grad_op)
    assert gs is not None and not solve_pays(gs)  # 61 fibers: the dense product is a few thousand steps


def _cuthill_mckee_one_at_a_time(ptr: np.ndarray, nbr: np.ndarray) -> np.ndarray:
    """The textbook reverse Cuthill-McKee: a queue, each fiber's unseen neighbours by degree (then number)."""
    n = ptr.size - 1
    degree = np.diff(ptr)
    seen = np.zeros(n, dtype=bool)
    out: list[int] = []

    def bfs(start: int, mark: np.ndarray) -> list[int]:
        order, head = [start], 0
        mark[start] = True
        while head < len(order):
            i = order[head]
            head += 1
            nb = nbr[ptr[i]:ptr[i + 1]]
            nb = nb[~mark[nb]]
            nb = nb[np.argsort(degree[nb], kind="stable")]
            mark[nb] = True
            order.extend(int(j) for j in nb)
        return order

    for start in np.argsort(degree, kind="stable"):
        if not seen[start]:
            out.extend(bfs(bfs(int(start), seen.copy())[-1], seen))
    return np.asarray(out[::-1])


@pytest.mark.parametrize("which", ["hex4", "irregular", "two arrays"])
def test_reverse_cuthill_mckee_a_level_at_a_time_is_the_textbook_order(which, request) -> None:
    if which == "two arrays":  # two components: each numbered from its own far fiber
        layout = request.getfixturevalue("hex4")
        tris, _ = _parts(layout)
        tris = np.concatenate([tris, tris + layout.n_fibers])
        n = 2 * layout.n_fibers
    else:
        layout = request.getfixturevalue(which)
        tris, _ = _parts(layout)
        n = layout.n_fibers
    ptr, nbr = neighbours(tris, n)
    assert np.array_equal(reverse_cuthill_mckee(ptr, nbr), _cuthill_mckee_one_at_a_time(ptr, nbr))
