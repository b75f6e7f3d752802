"""Accuracy of contact estimates against a recording's ground truth (pure functions).

The measurements are per frame (:class:`~optitac_edge.calibration.measure.Measurements`);
the truth is ``truth.csv``. A *press* is a run of consecutive contact frames
with the same true pose; repeatability and shape metrics are per frame, with
presses used to group repeated positions.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from optitac_edge.calibration.measure import Measurements
from optitac_edge.errors import RecordingError
from optitac_edge.io.recording import SHAPES, Truth

#: Repeated presses of one indenter closer than this (pitches; 0.2 mm on the paper's 1.5 mm array) count as
#: one position.
REPEAT_RADIUS_PITCH = 0.2 / 1.5
#: Widths are reported separately below and above this diameter (pitches), as in the paper (10 mm on its
#: 1.5 mm array).
WIDTH_SPLIT_PITCH = 10.0 / 1.5


def read_contacts_csv(path: str | Path) -> Measurements:
    """Read a contacts CSV written by ``optitac-edge replay`` back into arrays."""
    try:
        with Path(path).open(newline="") as f:
            rows = list(csv.DictReader(f))

        def col(name: str) -> np.ndarray:
            return np.array([float(r[name]) if r[name] else np.nan for r in rows])

        return Measurements(
            contact=np.array([r["contact"] == "1" for r in rows], dtype=bool),
            x_mm=col("x_mm"), y_mm=col("y_mm"), major_mm=col("major_mm"), minor_mm=col("minor_mm"),
            angle_deg=col("angle_deg"), strength=col("strength"), area_mm2=col("area_mm2"),
            peak=np.full(len(rows), np.nan),  # not a CSV column
            hu=np.stack([col(f"hu{k}") for k in range(1, 8)], axis=1) if rows else np.zeros((0, 7)),
            features=np.stack([col(f"hu{k}") for k in range(1, 8)] + [col("q4")], axis=1)
            if rows else np.zeros((0, 8)),
            shape=np.array([r["shape"] for r in rows], dtype=str), confidence=col("confidence"),
            # columns added later (issue 16): absent in older files
            depth_mm=col("depth_mm") if rows and "depth_mm" in rows[0] else None,
            force_n=col("force_n") if rows and "force_n" in rows[0] else None,
        )
    except (OSError, KeyError, ValueError) as exc:
        raise RecordingError(f"{path}: not a contacts CSV ({exc})") from None


def _r2(measured: np.ndarray, true: np.ndarray) -> float:
    ss_tot = float(np.sum((true - true.mean()) ** 2))
    return float(1.0 - np.sum((measured - true) ** 2) / ss_tot) if ss_tot > 0 else float("nan")


def _rmse(error: np.ndarray) -> float:
    return float(np.sqrt(np.mean(error**2))) if error.size else float("nan")


@dataclass(frozen=True)
class DetectionReport:
    """Contact detection against truth, in frames."""

    contact_frames: int
    detected: int
    rest_frames: int
    false_contacts: int

    @property
    def rate(self) -> float:
        return self.detected / self.contact_frames if self.contact_frames else float("nan")


@dataclass(frozen=True)
class CentroidReport:
    """Centroid error (measured − true) over true contact frames that were detected, mm."""

    n: int
    rmse_x: float
    rmse_y: float
    r2_x: float
    r2_y: float
    max_abs_x: float
    max_abs_y: float


@dataclass(frozen=True)
class RepeatPosition:
    """Repeated presses at one position: mean error and range (max − min) per axis, mm."""

    x_mm: float
    y_mm: float
    presses: int
    mean_error_x: float
    mean_error_y: float
    range_x: float
    range_y: float


@dataclass(frozen=True)
class WidthReport:
    """Width error of circular presses (measured − true diameter), mm, per axis."""

    n: int
    rmse_major: float
    rmse_minor: float
    r2_major: float
    r2_minor: float
    rmse_major_small: float
    rmse_minor_small: float
    rmse_major_large: float
    rmse_minor_large: float


@dataclass(frozen=True)
class ShapeReport:
    """Shape classification per contact frame."""

    classes: tuple[str, ...]
    confusion: np.ndarray  # (C, C) counts, rows true, columns predicted
    unclassified: np.ndarray  # (C,) frames of each true class given no (or another) shape
    f1: dict[str, float] = field(default_factory=dict)

    @property
    def normalised(self) -> np.ndarray:
        """Confusion as fractions of each true class's frames (unclassified ones included)."""
        rows = (self.confusion.sum(axis=1) + self.unclassified)[:, None]
        return np.divide(self.confusion, rows, out=np.zeros(self.confusion.shape), where=rows > 0)

    @property
    def average_diagonal(self) -> float:
        return float(np.mean(np.diag(self.normalised)))


def detection(m: Measurements, truth: Truth) -> DetectionReport:
    measured = m.contact[truth.frame]
    return DetectionReport(
        contact_frames=int(truth.contact.sum()), detected=int((measured & truth.contact).sum()),
        rest_frames=int((~truth.contact).sum()), false_contacts=int((measured & ~truth.contact).sum()),
    )


def detected_rows(m: Measurements, truth: Truth) -> np.ndarray:
    """Mask over truth rows: a true contact that was detected."""
    return truth.contact & m.contact[truth.frame]


def centroid_accuracy(m: Measurements, truth: Truth) -> CentroidReport:
    both = detected_rows(m, truth)
    frames = truth.frame[both]
    mx, my = m.x_mm[frames], m.y_mm[frames]
    tx, ty = truth.x_mm[both], truth.y_mm[both]
    ex, ey = mx - tx, my - ty
    return CentroidReport(
        n=int(both.sum()), rmse_x=_rmse(ex), rmse_y=_rmse(ey), r2_x=_r2(mx, tx), r2_y=_r2(my, ty),
        max_abs_x=float(np.abs(ex).max()) if ex.size else float("nan"),
        max_abs_y=float(np.abs(ey).max()) if ey.size else float("nan"),
    )


def press_ids(truth: Truth) -> np.ndarray:
    """Press number of every truth row (-1 for rest frames): runs of contact frames with one pose."""
    ids = np.full(len(truth), -1, dtype=np.int64)
    press = -1
    previous = None
    session = truth.session
    for k in range(len(truth)):
        if not truth.contact[k] or (session is not None and k and session[k] != session[k - 1]):
            previous = None  # a press never spans two recordings
        if not truth.contact[k]:
            continue
        # a blank cell (NaN, e.g. a circle's angle) is None: NaN != NaN made every frame a press of its own
        pose = tuple(None if isinstance(v, float) and math.isnan(v) else v for v in (
            str(truth.shape[k]), float(truth.x_mm[k]), float(truth.y_mm[k]), float(truth.angle_deg[k]),
            float(truth.size_mm[k])))
        if pose != previous:
            press += 1
            previous = pose
        ids[k] = press
    return ids


def repeatability(m: Measurements, truth: Truth, pitch_mm: float, min_presses: int = 5) -> list[RepeatPosition]:
    """Per repeated position: mean centroid error and its range over the presses there.

    Each press contributes the mean error of its detected frames; a position
    is at least ``min_presses`` presses of the same indenter (shape and size)
    whose true centres lie within :data:`REPEAT_RADIUS_PITCH` pitches (``pitch_mm``: the array's) of the first.
    """
    ids = press_ids(truth)
    both = detected_rows(m, truth)
    presses: list[tuple[float, float, float, float]] = []
    indenters: list[tuple[str, float]] = []
    for p in range(ids.max() + 1):
        rows = np.flatnonzero((ids == p) & both)
        if rows.size == 0:
            continue
        frames = truth.frame[rows]
        presses.append((truth.x_mm[rows[0]], truth.y_mm[rows[0]],
                        float(np.mean(m.x_mm[frames] - truth.x_mm[rows])),
                        float(np.mean(m.y_mm[frames] - truth.y_mm[rows]))))
        indenters.append((truth.shape[rows[0]], truth.size_mm[rows[0]]))
    if not presses:
        return []
    arr = np.array(presses)
    kind = np.array([hash(k) for k in indenters])
    unassigned = np.ones(len(arr), dtype=bool)
    positions = []
    for k in range(len(arr)):
        if not unassigned[k]:
            continue
        near = unassigned & (kind == kind[k]) & (
            np.hypot(arr[:, 0] - arr[k, 0], arr[:, 1] - arr[k, 1]) < REPEAT_RADIUS_PITCH * pitch_mm)
        unassigned &= ~near
        group = arr[near]
        if len(group) >= min_presses:
            positions.append(RepeatPosition(
                x_mm=float(group[:, 0].mean()), y_mm=float(group[:, 1].mean()), presses=len(group),
                mean_error_x=float(group[:, 2].mean()), mean_error_y=float(group[:, 3].mean()),
                range_x=float(np.ptp(group[:, 2])), range_y=float(np.ptp(group[:, 3]))))
    return positions


def width_accuracy(m: Measurements, truth: Truth, pitch_mm: float) -> WidthReport | None:
    """Width error over detected circular presses, below and above :data:`WIDTH_SPLIT_PITCH` pitches
    (``pitch_mm``: the array's) too; None without circles of two or more sizes."""
    rows = np.flatnonzero(detected_rows(m, truth) & (truth.shape == "circle"))
    if rows.size == 0 or np.unique(truth.size_mm[rows]).size < 2:
        return None
    frames = truth.frame[rows]
    true = truth.size_mm[rows]
    major, minor = m.major_mm[frames], m.minor_mm[frames]
    small = true < WIDTH_SPLIT_PITCH * pitch_mm
    return WidthReport(
        n=int(rows.size), rmse_major=_rmse(major - true), rmse_minor=_rmse(minor - true),
        r2_major=_r2(major, true), r2_minor=_r2(minor, true),
        rmse_major_small=_rmse((major - true)[small]), rmse_minor_small=_rmse((minor - true)[small]),
        rmse_major_large=_rmse((major - true)[~small]), rmse_minor_large=_rmse((minor - true)[~small]),
    )


@dataclass(frozen=True)
class DepthReport:
    """Depth (mm) and force (N) error over detected presses with a calibrated depth model.

    ``force_*`` are NaN without a force model or without ``force_n`` in the truth;
    ``force_range_n`` is the span of the true forces.
    """

    n: int
    depth_rmse_mm: float
    depth_bias_mm: float
    force_rmse_n: float
    force_range_n: float

    @property
    def force_rmse_pct(self) -> float:
        return 100.0 * self.force_rmse_n / self.force_range_n if self.force_range_n > 0 else float("nan")


def depth_accuracy(m: Measurements, truth: Truth, true_depth_mm: np.ndarray | None = None) -> DepthReport | None:
    """Depth and force error over detected presses; None without a depth model or presses at 2+ depths.

    ``true_depth_mm`` (shape (len(truth),)) replaces the truth's commanded depth (the simulator's real depths).
    """
    if m.depth_mm is None:
        return None
    rows = np.flatnonzero(detected_rows(m, truth))
    frames = truth.frame[rows]
    rows, frames = rows[np.isfinite(m.depth_mm[frames])], frames[np.isfinite(m.depth_mm[frames])]
    depth = (truth.depth_mm if true_depth_mm is None else np.asarray(true_depth_mm))[rows]
    if rows.size == 0 or np.unique(depth).size < 2:
        return None
    err = m.depth_mm[frames] - depth
    force_rmse = force_range = float("nan")
    if truth.force_n is not None and m.force_n is not None:
        true_f, got_f = truth.force_n[rows], m.force_n[frames]
        ok = np.isfinite(true_f) & np.isfinite(got_f)
        if ok.any():
            force_rmse, force_range = _rmse(got_f[ok] - true_f[ok]), float(np.ptp(true_f[ok]))
    return DepthReport(int(rows.size), _rmse(err), float(np.mean(err)), force_rmse, force_range)


def shape_accuracy(m: Measurements, truth: Truth) -> ShapeReport | None:
    """Confusion matrix and F1 over detected contact frames; None with fewer than two shapes."""
    rows = np.flatnonzero(detected_rows(m, truth))
    present = [s for s in SHAPES if np.any(truth.shape[rows] == s)]
    if len(present) < 2 or not np.any(m.shape[truth.frame[rows]] != ""):
        return None
    classes = tuple(present)
    index = {s: k for k, s in enumerate(classes)}
    confusion = np.zeros((len(classes), len(classes) + 1), dtype=np.int64)  # last column: other/none
    for r in rows:
        predicted = m.shape[truth.frame[r]]
        confusion[index[truth.shape[r]], index.get(predicted, len(classes))] += 1
    square = confusion[:, :-1]
    f1 = {}
    for k, s in enumerate(classes):
        tp = square[k, k]
        precision = tp / square[:, k].sum() if square[:, k].sum() else 0.0
        recall = tp / confusion[k].sum() if confusion[k].sum() else 0.0
        f1[s] = float(2 * precision * recall / (precision + recall)) if precision + recall else 0.0
    return ShapeReport(classes=classes, confusion=square, unclassified=confusion[:, -1], f1=f1)


def format_evaluation(m: Measurements, truth: Truth, pitch_mm: float) -> list[str]:
    """The metrics that apply to this recording (``pitch_mm``: the array's fiber pitch), as printable lines."""
    lines = []
    d = detection(m, truth)
    lines.append(f"detection: {d.detected}/{d.contact_frames} contact frames ({100 * d.rate:.1f} %), "
                 f"false contacts on {d.false_contacts}/{d.rest_frames} rest frames")
    c = centroid_accuracy(m, truth)
    if c.n:
        lines.append(f"centroid ({c.n} frames): RMSE x {c.rmse_x:.3f} mm, y {c.rmse_y:.3f} mm; "
                     f"R² x {c.r2_x:.4f}, y {c.r2_y:.4f}; max |error| x {c.max_abs_x:.3f}, y {c.max_abs_y:.3f} mm")
    positions = repeatability(m, truth, pitch_mm)
    if positions:
        lines.append("repeatability (position: presses, mean error x/y, range x/y, mm):")
        for p in positions:
            lines.append(f"  ({p.x_mm:+6.2f}, {p.y_mm:+6.2f}): {p.presses:2d}, "
                         f"{p.mean_error_x:+.3f}/{p.mean_error_y:+.3f}, {p.range_x:.3f}/{p.range_y:.3f}")
        lines.append(f"  average range x {np.mean([p.range_x for p in positions]):.3f} mm, "
                     f"y {np.mean([p.range_y for p in positions]):.3f} mm")
    w = width_accuracy(m, truth, pitch_mm)
    if w is not None:
        lines.append(f"width ({w.n} frames): RMSE major {w.rmse_major:.3f} mm, minor {w.rmse_minor:.3f} mm; "
                     f"R² major {w.r2_major:.4f}, minor {w.r2_minor:.4f}")
        lines.append(f"  below {WIDTH_SPLIT_PITCH * pitch_mm:.3g} mm: RMSE {w.rmse_major_small:.3f}/{w.rmse_minor_small:.3f} mm; "
                     f"above: {w.rmse_major_large:.3f}/{w.rmse_minor_large:.3f} mm")
    dr = depth_accuracy(m, truth)
    if dr is not None:
        line = f"depth ({dr.n} frames): RMSE {dr.depth_rmse_mm:.3f} mm, bias {dr.depth_bias_mm:+.3f} mm"
        if np.isfinite(dr.force_rmse_n):
            line += (f"; force RMSE {dr.force_rmse_n:.3f} N ({dr.force_rmse_pct:.1f} % of the "
                     f"{dr.force_range_n:.2f} N range)")
        lines.append(line)
    s = shape_accuracy(m, truth)
    if s is not None:
        lines.append(f"shapes: average diagonal {s.average_diagonal:.3f}; F1 "
                     + ", ".join(f"{k} {v:.2f}" for k, v in s.f1.items()))
        lines.append("  confusion (rows true, columns predicted, fraction of frames):")
        lines.append("  " + " " * 9 + " ".join(f"{c[:8]:>8}" for c in s.classes))
        for name, row in zip(s.classes, s.normalised):
            lines.append(f"  {name:>8} " + " ".join(f"{v:8.2f}" for v in row))
    return lines
