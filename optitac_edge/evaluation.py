"""Accuracy of contact estimates against a recording's ground truth (pure functions)."""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import RecordingError
from .recording import Truth


@dataclass(frozen=True)
class ContactColumns:
    """The columns of a contacts CSV needed for evaluation, one entry per frame (NaN: no contact)."""

    contact: np.ndarray  # (N,) bool
    x_mm: np.ndarray  # (N,) float64
    y_mm: np.ndarray
    major_mm: np.ndarray
    minor_mm: np.ndarray


def read_contacts_csv(path: str | Path) -> ContactColumns:
    """Read the columns of a contacts CSV written by ``optitac-edge replay``."""
    try:
        with Path(path).open(newline="") as f:
            rows = list(csv.DictReader(f))
        return ContactColumns(
            contact=np.array([r["contact"] == "1" for r in rows], dtype=bool),
            **{k: np.array([float(r[k]) if r[k] else np.nan for r in rows])
               for k in ("x_mm", "y_mm", "major_mm", "minor_mm")},
        )
    except (OSError, KeyError, ValueError) as exc:
        raise RecordingError(f"{path}: not a contacts CSV ({exc})") from None


@dataclass(frozen=True)
class DetectionReport:
    """Contact detection against truth, in frames."""

    contact_frames: int
    detected: int
    rest_frames: int
    false_contacts: int


@dataclass(frozen=True)
class CentroidReport:
    """Centroid error (measured minus true) over the truly-in-contact frames that were detected, mm."""

    n: int
    rmse_x: float
    rmse_y: float
    r2_x: float
    r2_y: float
    max_abs_x: float
    max_abs_y: float


def detection(contacts: ContactColumns, truth: Truth) -> DetectionReport:
    measured = contacts.contact[truth.frame]
    return DetectionReport(
        contact_frames=int(truth.contact.sum()), detected=int((measured & truth.contact).sum()),
        rest_frames=int((~truth.contact).sum()), false_contacts=int((measured & ~truth.contact).sum()),
    )


def _r2(measured: np.ndarray, true: np.ndarray) -> float:
    ss_tot = float(np.sum((true - true.mean()) ** 2))
    return float(1.0 - np.sum((measured - true) ** 2) / ss_tot) if ss_tot > 0 else float("nan")


def centroid_accuracy(contacts: ContactColumns, truth: Truth) -> CentroidReport:
    both = truth.contact & contacts.contact[truth.frame]
    frames = truth.frame[both]
    mx, my = contacts.x_mm[frames], contacts.y_mm[frames]
    tx, ty = truth.x_mm[both], truth.y_mm[both]
    ex, ey = mx - tx, my - ty
    return CentroidReport(
        n=int(both.sum()), rmse_x=float(np.sqrt(np.mean(ex**2))), rmse_y=float(np.sqrt(np.mean(ey**2))),
        r2_x=_r2(mx, tx), r2_y=_r2(my, ty),
        max_abs_x=float(np.abs(ex).max()), max_abs_y=float(np.abs(ey).max()),
    )
