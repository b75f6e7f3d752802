"""Custom fiber layouts as CSV files (``fiber,x_mm,y_mm``, see docs/formats.md)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from optitac_edge.core.layout import FiberLayout
from optitac_edge.errors import ConfigError
from optitac_edge.io.files import AtomicFile

LAYOUT_CSV_HEADER = ("fiber", "x_mm", "y_mm")


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
    with AtomicFile(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(LAYOUT_CSV_HEADER)
        for fid, (x, y) in zip(layout.ids, layout.xy_mm):
            w.writerow([int(fid), f"{x:.6f}", f"{y:.6f}"])
