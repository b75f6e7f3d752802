"""The contacts CSV written by ``optitac-edge replay`` (a contract, see docs/formats.md)."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import TYPE_CHECKING

from optitac_edge.io.files import AtomicFile

if TYPE_CHECKING:
    from typing_extensions import Self

    from optitac_edge.core.frame_result import FrameResult

CONTACTS_HEADER = (
    "frame", "contact", "x_mm", "y_mm", "major_mm", "minor_mm", "angle_deg", "strength",
    "shape", "confidence", "area_mm2", "hu1", "hu2", "hu3", "hu4", "hu5", "hu6", "hu7",
    "n_contacts", "q4", "t_ns", "depth_mm", "force_n", "contact_id",
    "vx_mm_s", "vy_mm_s", "sliding", "slide_frame", "vibration", "vibrating",
)


def _num(value: float, digits: int) -> str:
    return "" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


class ContactsCsvWriter:
    """Writes one row per processed frame; the file appears only when complete.

    Rows go to a private temporary file (:class:`~optitac_edge.io.files.AtomicFile`),
    renamed to ``path`` on a clean :meth:`close`; :meth:`abort` (or leaving a
    ``with`` block by an exception) removes it. ``path`` must be absent or a
    regular file; any failure to write raises
    :class:`~optitac_edge.errors.OutputError` naming it.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._out = AtomicFile(self.path, "w", newline="")
        self._csv = csv.writer(self._out)
        self._csv.writerow(CONTACTS_HEADER)

    def write(self, frame: int, result: FrameResult) -> None:
        """Append the row of frame ``frame`` from its :class:`~optitac_edge.core.frame_result.FrameResult`:
        the primary contact, the frame's contact count, capture time (ns) and vibration (NaN: not known)."""
        est, t_ns = result.primary, result.t_ns
        shaking = [_num(result.vibration, 3), int(bool(result.vibrating))]
        if not est.contact:
            self._csv.writerow([frame, 0, *([""] * 16), 0, "", int(t_ns), "", "", 0, "", "", 0, -1, *shaking])
            return
        self._csv.writerow([
            frame, 1, _num(est.x_mm, 4), _num(est.y_mm, 4), _num(est.major_mm, 4), _num(est.minor_mm, 4),
            _num(est.angle_deg, 3), _num(est.strength, 3), est.shape or "", _num(est.confidence, 4),
            _num(est.area_mm2, 3), *(_num(float(h), 6) for h in est.hu),
            result.n_contacts, _num(float(est.features[7]), 8), int(t_ns),
            _num(est.depth_mm, 4), _num(est.force_n, 4), int(est.contact_id),
            _num(est.vx_mm_s, 3), _num(est.vy_mm_s, 3), int(bool(est.sliding)), int(est.slide_frame), *shaking,
        ])

    def close(self) -> None:
        """Complete the file at ``path`` (idempotent)."""
        self._out.commit()

    def abort(self) -> None:
        """Drop the rows written; ``path`` is left as it was (idempotent)."""
        self._out.abort()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()
