"""Custom fiber layouts as CSV files (``fiber,x_mm,y_mm``, see docs/formats.md)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from optitac_edge.core.layout import FiberLayout
from optitac_edge.errors import ConfigError
from optitac_edge.io.files import AtomicFile

LAYOUT_CSV_HEADER = ("fiber", "x_mm", "y_mm")
#: Optional fourth column: ``dark`` or ``bright`` for fibers that are so by design, else empty.
FIDUCIAL_COLUMN = "fiducial"
FIDUCIAL_VALUES = {"": 0, "dark": -1, "bright": 1}
#: Largest layout file read (a fiber is one short line), bytes.
MAX_LAYOUT_BYTES = 4 << 20
#: Longest cell of a layout (a number), characters.
MAX_CELL_CHARS = 64
#: Largest fiber number.
MAX_FIBER_ID = 2**31 - 1


def load_layout_csv(path: str | Path) -> FiberLayout:  # noqa: C901
    """Read a custom layout from a CSV file with header ``fiber,x_mm,y_mm`` (UTF-8, a BOM allowed).

    An optional ``fiducial`` column marks fibers ``dark`` or ``bright`` by design.

    Raises
    ------
    ConfigError
        One line naming the file (and line) if it is missing, too large, not
        UTF-8 text, has another header, a cell too long or not a number, a fiber
        number outside 0..2**31-1 or repeated, two fibers at one position, or
        fewer than 7 fibers.
    """
    path = Path(path)
    try:
        if path.stat().st_size > MAX_LAYOUT_BYTES:
            raise ConfigError(f"{path}: larger than a layout can be ({MAX_LAYOUT_BYTES // 1024} KiB)")
        with path.open(newline="", encoding="utf-8-sig") as f:  # utf-8-sig: as Excel saves CSV
            rows = list(csv.reader(f))
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read layout ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.start})") from None
    except csv.Error as exc:
        raise ConfigError(f"{path}: not a CSV layout ({exc})") from None
    header = tuple(c.strip() for c in rows[0]) if rows else ()
    if header not in (LAYOUT_CSV_HEADER, (*LAYOUT_CSV_HEADER, FIDUCIAL_COLUMN)):
        raise ConfigError(f"{path}: layout header must be '{','.join(LAYOUT_CSV_HEADER)}' "
                          f"(optionally followed by ',{FIDUCIAL_COLUMN}')")
    ids, xy, fiducial = [], [], []
    for line_no, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise ConfigError(f"{path}: line {line_no}: expected {len(header)} cells, got {len(row)}")
        if len(header) > 3:
            mark = row[3].strip().lower()
            if mark not in FIDUCIAL_VALUES:
                raise ConfigError(f"{path}: line {line_no}: fiducial must be 'dark', 'bright' or empty, "
                                  f"not {row[3][:MAX_CELL_CHARS]!r}")
            fiducial.append(FIDUCIAL_VALUES[mark])
            row = row[:3]
        if any(len(c) > MAX_CELL_CHARS for c in row):
            raise ConfigError(f"{path}: line {line_no}: a cell longer than {MAX_CELL_CHARS} characters")
        try:
            fiber = int(row[0])
            xy.append((float(row[1]), float(row[2])))
        except ValueError:
            raise ConfigError(f"{path}: line {line_no}: not a number in {', '.join(row)}") from None
        if not 0 <= fiber <= MAX_FIBER_ID:
            raise ConfigError(f"{path}: line {line_no}: fiber number {row[0].strip()} outside 0..{MAX_FIBER_ID}")
        ids.append(fiber)
    if len(set(ids)) != len(ids):
        raise ConfigError(f"{path}: duplicate fiber number")
    if len(ids) < 7:
        raise ConfigError(f"{path}: a layout needs at least 7 fibers, found {len(ids)}")
    xy_arr = np.asarray(xy, dtype=np.float64)
    if not np.all(np.isfinite(xy_arr)):
        raise ConfigError(f"{path}: non-finite coordinate")
    try:
        return FiberLayout(ids=np.asarray(ids, dtype=np.int64), xy_mm=xy_arr,
                           fiducial=np.asarray(fiducial, dtype=np.int8) if len(header) > 3 else None)
    except ValueError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def save_layout_csv(layout: FiberLayout, path: str | Path) -> None:
    """Write ``layout`` as a CSV file with header ``fiber,x_mm,y_mm`` (and ``fiducial`` when it has them)."""
    names = {v: k for k, v in FIDUCIAL_VALUES.items()}
    with AtomicFile(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(LAYOUT_CSV_HEADER + ((FIDUCIAL_COLUMN,) if layout.fiducial is not None else ()))
        for k, (fid, (x, y)) in enumerate(zip(layout.ids, layout.xy_mm)):
            mark = [] if layout.fiducial is None else [names[int(layout.fiducial[k])]]
            w.writerow([int(fid), f"{x:.6f}", f"{y:.6f}", *mark])
