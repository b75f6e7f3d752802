"""The sensor's CAD layout: where each fiber sits on the skin, in millimetres.

Sensor frame: origin at the central fiber, +x along the rows of fibers, +y up
(90 degrees counter-clockwise from +x), coordinates in mm.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from optitac_edge.errors import ConfigError

#: Header a custom layout CSV must have, in this order.
LAYOUT_CSV_HEADER = ("fiber", "x_mm", "y_mm")


@dataclass(frozen=True, eq=False)
class FiberLayout:
    """Fiber positions of one sensor.

    Attributes
    ----------
    ids : ndarray, shape (N,), int64
        Fiber numbers as printed on the CAD drawing (any unique integers).
    xy_mm : ndarray, shape (N, 2), float64
        Fiber centres in the sensor frame, mm.
    """

    ids: np.ndarray
    xy_mm: np.ndarray

    def __post_init__(self) -> None:
        if self.xy_mm.ndim != 2 or self.xy_mm.shape[1] != 2:
            raise ValueError("xy_mm must have shape (N, 2)")
        if self.ids.shape != (self.xy_mm.shape[0],):
            raise ValueError("ids must have shape (N,)")

    @property
    def n_fibers(self) -> int:
        return int(self.xy_mm.shape[0])

    @property
    def pitch_mm(self) -> float:
        """Median nearest-neighbour distance between fibers, mm."""
        d = np.linalg.norm(self.xy_mm[:, None, :] - self.xy_mm[None, :, :], axis=-1)
        np.fill_diagonal(d, np.inf)
        return float(np.median(d.min(axis=1)))

    @property
    def radius_mm(self) -> float:
        """Distance of the outermost fiber centre from the origin, mm."""
        return float(np.linalg.norm(self.xy_mm, axis=1).max())

    def neighbours(self, max_distance_mm: float | None = None) -> list[np.ndarray]:
        """Indices of each fiber's neighbours within ``max_distance_mm``.

        The default distance is 1.2 pitches, i.e. the six hexagonal neighbours.
        """
        limit = 1.2 * self.pitch_mm if max_distance_mm is None else max_distance_mm
        d = np.linalg.norm(self.xy_mm[:, None, :] - self.xy_mm[None, :, :], axis=-1)
        np.fill_diagonal(d, np.inf)
        return [np.flatnonzero(row <= limit) for row in d]


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


def load_layout_csv(path: str | Path) -> FiberLayout:
    """Read a custom layout from a CSV file with header ``fiber,x_mm,y_mm``.

    Raises
    ------
    ConfigError
        If the file is missing, has another header, a bad number, a duplicate
        fiber number, or fewer than 7 fibers.
    """
    path = Path(path)
    try:
        with path.open(newline="") as f:
            rows = list(csv.reader(f))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read layout ({exc.strerror or exc})") from None
    if not rows or tuple(c.strip() for c in rows[0]) != LAYOUT_CSV_HEADER:
        raise ConfigError(f"{path}: layout header must be '{','.join(LAYOUT_CSV_HEADER)}'")
    ids, xy = [], []
    for line_no, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != 3:
            raise ConfigError(f"{path}: line {line_no}: expected 3 cells, got {len(row)}")
        try:
            ids.append(int(row[0]))
            xy.append((float(row[1]), float(row[2])))
        except ValueError:
            raise ConfigError(f"{path}: line {line_no}: not a number in {row!r}") from None
    if len(set(ids)) != len(ids):
        raise ConfigError(f"{path}: duplicate fiber number")
    if len(ids) < 7:
        raise ConfigError(f"{path}: a layout needs at least 7 fibers, found {len(ids)}")
    xy_arr = np.asarray(xy, dtype=np.float64)
    if not np.all(np.isfinite(xy_arr)):
        raise ConfigError(f"{path}: non-finite coordinate")
    return FiberLayout(ids=np.asarray(ids, dtype=np.int64), xy_mm=xy_arr)


def save_layout_csv(layout: FiberLayout, path: str | Path) -> None:
    """Write ``layout`` as a CSV file with header ``fiber,x_mm,y_mm``."""
    with Path(path).open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(LAYOUT_CSV_HEADER)
        for fid, (x, y) in zip(layout.ids, layout.xy_mm):
            w.writerow([int(fid), f"{x:.6f}", f"{y:.6f}"])
