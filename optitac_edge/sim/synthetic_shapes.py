"""Synthetic labelled shape features: binary shapes rasterised on the surface mesh.

For tests and demos of the shape classifier without a sensor. Each sample is
the five-shape set of the simulator (edge bar 12 mm long, 1.5-2 mm wide;
circle, square, ellipse (ratio 0.6) and equilateral triangle, 4-8 mm by
default) at a random position and angle, with rounded corners and a wobbly
outline (the binarised contact surface is smooth), rasterised on a 100 x 100
:class:`~optitac_edge.core.grid.SurfaceGrid`, optionally blurred by a Gaussian
(the skin) and binarised again at a fraction of its peak. Features are
``[log-Hu x 7, q4]`` as ``ContactEstimate.features``:
:func:`~optitac_edge.core.moments.log_hu` of :func:`~optitac_edge.core.moments.hu_moments`
and :func:`~optitac_edge.core.moments.q4_moment`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import gaussian_filter

from optitac_edge.core.grid import SurfaceGrid
from optitac_edge.core.moments import hu_moments, log_hu, q4_moment
from optitac_edge.io.recording import SHAPES

#: The default mesh: 100 x 100 cells spanning +-12 mm (the default layout's).
DEFAULT_GRID = SurfaceGrid(n=100, x0_mm=-12.0, y0_mm=-12.0, step_mm=24.0 / 99)


def _sdf(shape: str, px: np.ndarray, py: np.ndarray, size: float, shrink: float) -> np.ndarray:
    """Signed distance (mm, < 0 inside) to the shape shrunk by ``shrink`` (rounded corners)."""
    if shape == "circle":
        return np.hypot(px, py) - size / 2
    if shape in ("square", "edge"):
        hx, hy = (size / 2, size / 2) if shape == "square" else (6.0, size / 2)
        qx, qy = np.abs(px) - (hx - shrink), np.abs(py) - (hy - shrink)
        outside = np.hypot(np.maximum(qx, 0), np.maximum(qy, 0))
        return outside + np.minimum(np.maximum(qx, qy), 0) - shrink
    if shape == "ellipse":
        a, b = size / 2, 0.6 * size / 2
        return (np.hypot(px / a, py / b) - 1.0) * b  # approximate distance, exact zero set
    # equilateral triangle, centroid at 0: max of the three edge half-plane distances
    r_in = size / (2 * math.sqrt(3))
    d = np.full(px.shape, -np.inf)
    for t in (math.pi / 2, math.pi / 2 + 2 * math.pi / 3, math.pi / 2 + 4 * math.pi / 3):
        d = np.maximum(d, -(px * math.cos(t) + py * math.sin(t)) - r_in)
    return d


def shape_mask(
    shape: str, x_mm: float, y_mm: float, angle_deg: float, size_mm: float,
    grid: SurfaceGrid = DEFAULT_GRID, round_mm: float = 0.0, wobble: np.ndarray | None = None,
) -> np.ndarray:
    """Binary mask of one shape on the mesh.

    Parameters
    ----------
    shape : str
        One of ``SHAPES``.
    x_mm, y_mm, angle_deg, size_mm : float
        Centre (mm), counter-clockwise rotation (degrees), size (mm: diameter,
        side, major axis or bar width).
    grid : SurfaceGrid
    round_mm : float
        Corner rounding radius of square / edge, mm.
    wobble : ndarray, shape (n, n), float64, optional
        Added to the signed distance (mm): a smooth random field roughens the outline.

    Returns
    -------
    ndarray, shape (n, n), bool
    """
    xx, yy = np.meshgrid(grid.x_mm, grid.y_mm)
    t = math.radians(angle_deg)
    dx, dy = xx - x_mm, yy - y_mm
    px, py = math.cos(t) * dx + math.sin(t) * dy, -math.sin(t) * dx + math.cos(t) * dy
    sdf = _sdf(shape, px, py, size_mm, round_mm)
    if wobble is not None:
        sdf = sdf + wobble
    return sdf < 0.0


def synthetic_features(
    n_per_class: int, seed: int = 0, shapes: tuple[str, ...] = SHAPES, wobble_mm: float = 0.1, hu_noise: float = 0.0,
    size_mm: tuple[float, float] = (4.0, 8.0), blur_mm: float = 0.0, level: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """Labelled shape features ``[log-Hu x 7, q4]`` of random shapes on :data:`DEFAULT_GRID`.

    Parameters
    ----------
    n_per_class : int
    seed : int
    shapes : tuple of str
    wobble_mm : float
        Standard deviation of the outline roughness, mm (0: clean rasterisation).
    hu_noise : float
        Gaussian noise added to the log-Hu values (dimensionless; 0: none; q4 is left as is).
    size_mm : (float, float)
        Size range of all shapes but the edge (diameter, side, major axis), mm.
    blur_mm : float
        Standard deviation of the Gaussian blur, mm (0: none).
    level : float
        The blurred mask is binarised at ``level`` times its peak.

    Returns
    -------
    features : ndarray, shape (n_per_class * len(shapes), 8), float64
        As ``ContactEstimate.features``: 7 log-Hu values then q4.
    labels : ndarray, shape (n_per_class * len(shapes),), str
        Class-sorted order.
    """
    grid = DEFAULT_GRID
    rng = np.random.default_rng(seed)
    period = {"circle": 360.0, "square": 90.0, "triangle": 120.0, "ellipse": 180.0, "edge": 180.0}
    out, labels = [], []
    for shape in shapes:
        for _ in range(n_per_class):
            size = rng.uniform(1.5, 2.0) if shape == "edge" else rng.uniform(*size_mm)
            reach = 6.5 if shape == "edge" else size / 1.7
            room = max(11.0 - reach, 0.0)
            x, y = rng.uniform(-room, room, 2) / math.sqrt(2)
            wobble = None
            if wobble_mm > 0:
                field = gaussian_filter(rng.standard_normal((grid.n, grid.n)), 4.0)
                wobble = field * (wobble_mm / max(field.std(), 1e-12))
            mask = shape_mask(shape, float(x), float(y), float(rng.uniform(0, period[shape])),
                              float(size), grid, round_mm=float(rng.uniform(0.0, 0.4)) * size / 4,
                              wobble=wobble)
            if blur_mm > 0:
                soft = gaussian_filter(mask.astype(np.float64), blur_mm / grid.step_mm)
                mask = soft > level * soft.max()
            out.append(np.append(log_hu(hu_moments(mask, grid)), q4_moment(mask, grid)))
            labels.append(shape)
    f = np.array(out)
    if hu_noise > 0:
        f[:, :7] += rng.normal(0.0, hu_noise, (f.shape[0], 7))
    return f, np.array(labels)
