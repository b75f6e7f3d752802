"""The sensor's CAD layout: where each fiber sits on the skin, in millimetres.

Sensor frame: origin at the central fiber, +x along the rows of fibers, +y up
(90 degrees counter-clockwise from +x), coordinates in mm.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

#: Fewest fibers a layout may have (the surface needs a triangulation).
MIN_FIBERS = 7
#: A fiber farther from the centre than this (mm) is a layout in other units (or garbage).
MAX_EXTENT_MM = 1000.0
#: Fibers closer than this (mm) are a layout in other units: no fiber array is that dense.
MIN_SPACING_MM = 0.01
#: The paper's array pitch, mm: the simulator's skin and the experiments' indenters are sized for it, and scale
#: with another array's pitch (:func:`pitch_scale`).
PAPER_PITCH_MM = 1.5


#: The cell offsets that, with a cell's own, reach every pair of points in neighbouring cells once.
_HALF_NEIGHBOURHOOD = ((0, 0), (1, -1), (1, 0), (1, 1), (0, 1))


def pairs_within(xy: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """Every pair of points at most ``limit`` apart, each once, and their distances.

    Points are binned into square cells of side ``limit``; only points of a cell and its neighbours are
    compared, so time and memory grow with the number of points and pairs, never as N x N.

    Parameters
    ----------
    xy : ndarray, shape (N, 2), float64
    limit : float
        > 0, in ``xy``'s units.

    Returns
    -------
    pairs : ndarray, shape (P, 2), intp
        ``(i, j)`` with ``i != j``.
    distance : ndarray, shape (P,), float64
    """
    n = xy.shape[0]
    empty = (np.zeros((0, 2), dtype=np.intp), np.zeros(0))
    if n < 2 or not limit > 0:
        return empty
    origin = xy.min(axis=0)
    cell = np.floor((xy - origin) / limit).astype(np.int64)
    width = int(cell[:, 1].max()) + 3
    key = (cell[:, 0] + 1) * width + (cell[:, 1] + 1)  # +1: the offsets' cells never go below 0
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    found_i, found_j = [], []
    for dx, dy in _HALF_NEIGHBOURHOOD:
        target = key + dx * width + dy
        lo = np.searchsorted(sorted_key, target, side="left")
        hi = np.searchsorted(sorted_key, target, side="right")
        count = hi - lo
        total = int(count.sum())
        if total == 0:
            continue
        i = np.repeat(np.arange(n), count)
        first = np.repeat(lo - np.r_[0, np.cumsum(count)[:-1]], count)
        j = order[np.arange(total) + first]
        keep = i < j if (dx, dy) == (0, 0) else np.ones(total, dtype=bool)
        found_i.append(i[keep])
        found_j.append(j[keep])
    if not found_i:
        return empty
    i, j = np.concatenate(found_i), np.concatenate(found_j)
    d = np.hypot(*(xy[i] - xy[j]).T)
    close = d <= limit
    return np.stack([i[close], j[close]], axis=1).astype(np.intp), d[close]


def nearest_distances(xy: np.ndarray) -> np.ndarray:
    """Each point's distance to its nearest other point, shape (N,) (inf for a single point)."""
    n = xy.shape[0]
    nearest = np.full(n, np.inf)
    if n < 2:
        return nearest
    span = float(np.ptp(xy, axis=0).max())
    limit = max(span / np.sqrt(n), MIN_SPACING_MM) * 1.5  # about a pitch and a half on an even array
    while True:
        pairs, d = pairs_within(xy, limit)
        np.minimum.at(nearest, pairs[:, 0], d)
        np.minimum.at(nearest, pairs[:, 1], d)
        if np.all(np.isfinite(nearest)) or limit > 2.0 * span:
            return nearest
        limit *= 2.0


@dataclass(frozen=True, eq=False)
class FiberLayout:
    """Fiber positions of one sensor.

    Attributes
    ----------
    ids : ndarray, shape (N,), int64
        Fiber numbers as printed on the CAD drawing (any unique integers).
    xy_mm : ndarray, shape (N, 2), float64
        Fiber centres in the sensor frame, mm.
    fiducial : ndarray, shape (N,), int8, or None
        Fibers dark (-1) or bright (+1) by design, 0 for the others; they let
        fiber calibration tell the layout's symmetries apart from rest frames.
    """

    ids: np.ndarray
    xy_mm: np.ndarray
    fiducial: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.xy_mm.ndim != 2 or self.xy_mm.shape[1] != 2:
            raise ValueError("xy_mm must have shape (N, 2)")
        if self.ids.shape != (self.xy_mm.shape[0],):
            raise ValueError("ids must have shape (N,)")
        if self.xy_mm.shape[0] < MIN_FIBERS:
            raise ValueError(f"a layout needs at least {MIN_FIBERS} fibers, got {self.xy_mm.shape[0]}")
        if not np.all(np.isfinite(self.xy_mm)):
            raise ValueError("fiber positions must be finite")
        if np.abs(self.xy_mm).max() > MAX_EXTENT_MM:
            raise ValueError(f"fiber positions must lie within {MAX_EXTENT_MM:g} mm of the centre (mm, not um?)")
        if np.unique(self.ids).size != self.ids.size:
            raise ValueError("fiber ids must be unique")
        if np.unique(self.xy_mm, axis=0).shape[0] != self.xy_mm.shape[0]:
            raise ValueError("two fibers at the same position")
        close, spacing = pairs_within(self.xy_mm, MIN_SPACING_MM)
        if close.shape[0]:
            nearest = float(spacing.min())
            raise ValueError(f"two fibers {nearest:.3g} mm apart: fibers are at least {MIN_SPACING_MM:g} mm apart "
                             "(mm, not m?)")
        centred = self.xy_mm - self.xy_mm.mean(axis=0)
        spread = np.linalg.svd(centred, compute_uv=False)
        if not spread[1] > 1e-9 * max(float(spread[0]), MIN_SPACING_MM):
            raise ValueError("the fibers lie on one line: a layout is a 2-D array (its surface needs triangles)")
        if self.fiducial is not None and (self.fiducial.shape != self.ids.shape
                                          or not np.all(np.isin(self.fiducial, (-1, 0, 1)))):
            raise ValueError("fiducial must have shape (N,) and values -1 (dark), 0 or +1 (bright)")

    @property
    def n_fibers(self) -> int:
        return int(self.xy_mm.shape[0])

    @functools.cached_property
    def pitch_mm(self) -> float:
        """Median nearest-neighbour distance between fibers, mm (computed once: a layout is not changed)."""
        return float(np.median(nearest_distances(self.xy_mm)))

    @property
    def radius_mm(self) -> float:
        """Distance of the outermost fiber centre from the origin, mm."""
        return float(np.linalg.norm(self.xy_mm, axis=1).max())

    def neighbours(self, max_distance_mm: float | None = None) -> list[np.ndarray]:
        """Indices of each fiber's neighbours within ``max_distance_mm``.

        The default distance is 1.2 pitches, i.e. the six hexagonal neighbours.
        """
        pairs = self.neighbour_pairs(max_distance_mm)
        both = np.concatenate([pairs, pairs[:, ::-1]])
        both = both[np.lexsort((both[:, 1], both[:, 0]))]
        starts = np.searchsorted(both[:, 0], np.arange(self.n_fibers + 1))
        return [both[starts[k]:starts[k + 1], 1] for k in range(self.n_fibers)]

    def neighbour_pairs(self, max_distance_mm: float | None = None) -> np.ndarray:
        """Each pair of neighbouring fibers once (within ``max_distance_mm``; default 1.2 pitches, the six
        hexagonal neighbours), shape (P, 2), intp."""
        limit = 1.2 * self.pitch_mm if max_distance_mm is None else max_distance_mm
        return pairs_within(self.xy_mm, limit)[0]


def hex_layout(rings: int = 8, pitch_mm: float = 1.5) -> FiberLayout:
    """The default hexagonal layout: a central fiber and ``rings`` rings around it.

    Rows of fibers run parallel to x. Fibers are numbered row by row from the
    top row (largest y) down, left to right within a row; with 8 rings that is
    217 fibers and the central fiber is number 108.

    Parameters
    ----------
    rings : int
        Number of hexagonal rings around the central fiber.
    pitch_mm : float
        Centre-to-centre distance of neighbouring fibers, mm.
    """
    if rings < 1 or pitch_mm <= 0:
        raise ValueError("rings must be >= 1 and pitch_mm > 0")
    row_height = pitch_mm * np.sqrt(3.0) / 2.0
    points = []
    for row in range(rings, -rings - 1, -1):  # top row first
        count = 2 * rings + 1 - abs(row)
        x0 = -(count - 1) * pitch_mm / 2.0
        for k in range(count):
            points.append((x0 + k * pitch_mm, row * row_height))
    xy = np.asarray(points, dtype=np.float64)
    xy[np.abs(xy) < 1e-12] = 0.0
    return FiberLayout(ids=np.arange(len(xy), dtype=np.int64), xy_mm=xy)


def pitch_scale(layout: FiberLayout) -> float:
    """The layout's pitch in units of :data:`PAPER_PITCH_MM` (1 for the paper's array)."""
    return layout.pitch_mm / PAPER_PITCH_MM


def scaled_mm(value_mm: float, scale: float) -> float:
    """A length sized for the paper's array, for an array ``scale`` times its pitch: as it is at scale 1,
    else to the nearest 0.05 mm (an indenter one can make)."""
    return value_mm if scale == 1.0 else round(value_mm * scale * 20.0) / 20.0
