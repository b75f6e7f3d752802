"""Recordings: a directory of frames plus metadata and optional ground truth.

Layout of a recording directory (a contract; see docs/formats.md):

``frames.npy``  uint8, shape (N, H, W) gray or (N, H, W, 3) RGB; opened
                memory-mapped and streamed, never loaded whole.
``meta.json``   at least ``rest_frames`` (int >= 5, leading contact-free
                frames) and ``fps`` (> 0); other keys are kept as ``extra``.
``truth.csv``   optional, header
                ``frame,contact,shape,x_mm,y_mm,angle_deg,size_mm,depth_mm``.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from optitac_edge.core.frames import infer_pixel_format
from optitac_edge.errors import FrameMismatchError, RecordingError

if TYPE_CHECKING:
    from typing_extensions import Self

TRUTH_HEADER = ("frame", "contact", "shape", "x_mm", "y_mm", "angle_deg", "size_mm", "depth_mm")
SHAPES = ("edge", "circle", "square", "ellipse", "triangle")
MIN_REST_FRAMES = 5


@dataclass(frozen=True)
class RecordingMeta:
    """``meta.json`` of a recording."""

    rest_frames: int
    fps: float
    extra: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"rest_frames": self.rest_frames, "fps": self.fps, **self.extra}


@dataclass(frozen=True, eq=False)
class Truth:
    """Ground truth per frame (columns of ``truth.csv``); NaN / '' where no contact."""

    frame: np.ndarray  # (N,) int64
    contact: np.ndarray  # (N,) bool
    shape: np.ndarray  # (N,) str ('' when no contact)
    x_mm: np.ndarray  # (N,) float64
    y_mm: np.ndarray
    angle_deg: np.ndarray
    size_mm: np.ndarray
    depth_mm: np.ndarray

    def __len__(self) -> int:
        return int(self.frame.shape[0])


def _write_json_atomic(path: Path, obj: Any) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w") as f:
        json.dump(obj, f, indent=2)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def read_meta(path: Path) -> RecordingMeta:
    """Parse and validate ``meta.json``."""
    try:
        raw = json.loads(path.read_text())
    except FileNotFoundError:
        raise RecordingError(f"{path.parent}: not a recording (no meta.json)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RecordingError(f"{path}: garbled meta.json ({exc})") from None
    if not isinstance(raw, dict):
        raise RecordingError(f"{path}: meta.json must hold an object")
    rest = raw.pop("rest_frames", None)
    fps = raw.pop("fps", None)
    if not isinstance(rest, int) or isinstance(rest, bool) or rest < MIN_REST_FRAMES:
        raise RecordingError(f"{path}: 'rest_frames' must be an integer >= {MIN_REST_FRAMES}")
    if not isinstance(fps, (int, float)) or isinstance(fps, bool) or not (fps > 0 and math.isfinite(fps)):
        raise RecordingError(f"{path}: 'fps' must be a positive number")
    return RecordingMeta(rest_frames=rest, fps=float(fps), extra=raw)


def _cell_float(value: str) -> float:
    return float(value) if value.strip() else math.nan


def read_truth(path: Path, n_frames: int) -> Truth:
    """Parse and validate ``truth.csv`` against a recording of ``n_frames`` frames."""
    try:
        with path.open(newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{path}: cannot read truth ({exc})") from None
    if not rows or tuple(c.strip() for c in rows[0]) != TRUTH_HEADER:
        raise RecordingError(f"{path}: header must be '{','.join(TRUTH_HEADER)}'")
    cols: list[list[Any]] = [[] for _ in TRUTH_HEADER]
    for line_no, row in enumerate(rows[1:], start=2):
        if len(row) != len(TRUTH_HEADER):
            raise RecordingError(f"{path}: line {line_no}: expected {len(TRUTH_HEADER)} cells")
        try:
            frame, contact = int(row[0]), int(row[1])
            values = [_cell_float(c) for c in row[3:]]
        except ValueError:
            raise RecordingError(f"{path}: line {line_no}: not a number") from None
        shape = row[2].strip()
        if not 0 <= frame < n_frames or contact not in (0, 1):
            raise RecordingError(f"{path}: line {line_no}: frame or contact out of range")
        if contact and shape not in SHAPES:
            raise RecordingError(f"{path}: line {line_no}: unknown shape {shape!r}")
        for col, value in zip(cols, [frame, bool(contact), shape if contact else "", *values]):
            col.append(value)
    return Truth(
        frame=np.asarray(cols[0], dtype=np.int64),
        contact=np.asarray(cols[1], dtype=bool),
        shape=np.asarray(cols[2], dtype=str),
        **{name: np.asarray(c, dtype=np.float64) for name, c in zip(TRUTH_HEADER[3:], cols[3:])},
    )


class Recording:
    """A recording opened for streaming. Frames are memory-mapped, never loaded whole.

    Parameters
    ----------
    path : path-like
        The recording directory.

    Raises
    ------
    RecordingError
        If the directory, ``frames.npy`` or ``meta.json`` is missing or garbled.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_dir():
            raise RecordingError(f"{self.path}: recording directory not found")
        self.meta = read_meta(self.path / "meta.json")
        frames_path = self.path / "frames.npy"
        try:
            frames = np.load(frames_path, mmap_mode="r", allow_pickle=False)
        except FileNotFoundError:
            raise RecordingError(f"{self.path}: not a recording (no frames.npy)") from None
        except (OSError, ValueError, EOFError) as exc:
            raise RecordingError(f"{frames_path}: garbled or truncated frames ({exc})") from None
        if frames.dtype != np.uint8 or frames.ndim not in (3, 4) or frames.shape[0] < 1:
            raise RecordingError(
                f"{frames_path}: frames must be uint8 (N,H,W) or (N,H,W,3), "
                f"got {frames.dtype} {frames.shape}"
            )
        try:
            self.pixel_format = infer_pixel_format(frames.shape[1:])
        except FrameMismatchError:
            raise RecordingError(f"{frames_path}: frames of shape {frames.shape} are not gray or RGB") from None
        self.frames = frames
        if self.meta.rest_frames > len(frames):
            raise RecordingError(f"{self.path}: rest_frames={self.meta.rest_frames} but only {len(frames)} frames")
        truth_path = self.path / "truth.csv"
        self.truth: Truth | None = read_truth(truth_path, len(frames)) if truth_path.exists() else None

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    @property
    def frame_shape(self) -> tuple[int, ...]:
        """Array shape of one frame."""
        return tuple(int(s) for s in self.frames.shape[1:])

    @property
    def height(self) -> int:
        return int(self.frames.shape[1])

    @property
    def width(self) -> int:
        return int(self.frames.shape[2])

    def rest_frames(self) -> np.ndarray:
        """The leading contact-free frames (a memory-mapped view)."""
        return self.frames[: self.meta.rest_frames]

    def __iter__(self) -> Iterator[np.ndarray]:
        for i in range(len(self)):
            yield self.frames[i]

    def frame(self, index: int) -> np.ndarray:
        """Frame ``index`` as a C-contiguous array in memory."""
        return np.ascontiguousarray(self.frames[index])


class RecordingWriter:
    """Streams frames into a new recording directory.

    ``frames.npy`` is preallocated for ``n_frames`` and written through a
    memory map; ``meta.json`` is written last, on :meth:`close`, so a recording
    cut short is recognisably incomplete.
    """

    def __init__(
        self,
        path: str | Path,
        n_frames: int,
        frame_shape: tuple[int, ...],
        meta: RecordingMeta,
        with_truth: bool = False,
    ) -> None:
        self.path = Path(path)
        self.path.mkdir(parents=True, exist_ok=True)
        for stale in ("meta.json", "truth.csv"):
            (self.path / stale).unlink(missing_ok=True)
        infer_pixel_format(frame_shape)
        self.meta = meta
        self._frames = np.lib.format.open_memmap(
            self.path / "frames.npy", mode="w+", dtype=np.uint8, shape=(n_frames, *frame_shape)
        )
        self._truth_rows: list[list[str]] | None = [] if with_truth else None
        self._closed = False

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def write(self, index: int, frame: np.ndarray) -> None:
        self._frames[index] = frame

    def write_truth(
        self,
        frame: int,
        contact: bool,
        shape: str = "",
        x_mm: float = math.nan,
        y_mm: float = math.nan,
        angle_deg: float = math.nan,
        size_mm: float = math.nan,
        depth_mm: float = math.nan,
    ) -> None:
        if self._truth_rows is None:
            raise ValueError("writer was opened without truth")

        def cell(v: float) -> str:
            return "" if not contact or math.isnan(v) else f"{v:.4f}"

        self._truth_rows.append(
            [str(frame), str(int(contact)), shape if contact else "",
             *(cell(v) for v in (x_mm, y_mm, angle_deg, size_mm, depth_mm))]
        )

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._frames.flush()
        del self._frames
        if self._truth_rows is not None:
            tmp = self.path / "truth.csv.tmp"
            with tmp.open("w", newline="") as f:
                w = csv.writer(f)
                w.writerow(TRUTH_HEADER)
                w.writerows(self._truth_rows)
            os.replace(tmp, self.path / "truth.csv")
        _write_json_atomic(self.path / "meta.json", self.meta.to_json())
