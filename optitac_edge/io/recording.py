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
import errno
import json
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from optitac_edge.core.frames import infer_pixel_format
from optitac_edge.errors import FrameMismatchError, OutputError, RecordingError
from optitac_edge.io.files import AtomicFile, check_output_path, fsync_directory, write_file_atomic

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


#: Largest truth.csv read, bytes (a row a frame).
MAX_TRUTH_BYTES = 64 << 20
#: Largest meta.json read, bytes (it holds a few numbers and the simulator's parameters).
MAX_META_BYTES = 1 << 20
#: The frame rates a recording may claim, frames/s.
FPS_RANGE = (0.1, 10_000.0)
#: Written instead of meta.json by a writer that did not finish (see RecordingWriter).
INCOMPLETE_MARKER = "incomplete.json"


def read_meta(path: Path) -> RecordingMeta:
    """Parse and validate ``meta.json``.

    Raises
    ------
    RecordingError
        If it is missing (the recording is incomplete or not one), unreadable,
        too large, not a JSON object, or ``rest_frames`` / ``fps`` are out of range.
    """
    try:
        size = path.stat().st_size
        if size > MAX_META_BYTES:
            raise RecordingError(f"{path}: {size} bytes, larger than a meta.json can be ({MAX_META_BYTES})")
        raw = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RecordingError(f"{path.parent}: {_missing_meta(path.parent)}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, ValueError, RecursionError) as exc:
        why = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        raise RecordingError(f"{path}: garbled meta.json ({why})") from None
    if not isinstance(raw, dict):
        raise RecordingError(f"{path}: meta.json must hold an object")
    rest = raw.pop("rest_frames", None)
    fps = raw.pop("fps", None)
    if not isinstance(rest, int) or isinstance(rest, bool) or not MIN_REST_FRAMES <= rest <= 1_000_000_000:
        raise RecordingError(f"{path}: 'rest_frames' must be an integer >= {MIN_REST_FRAMES}")
    lo, hi = FPS_RANGE
    if not isinstance(fps, (int, float)) or isinstance(fps, bool) or not lo <= fps <= hi:
        raise RecordingError(f"{path}: 'fps' must be a number in {lo:g}..{hi:g}")
    return RecordingMeta(rest_frames=rest, fps=float(fps), extra=raw)


def _missing_meta(directory: Path) -> str:
    """Why a directory without meta.json is not a usable recording."""
    marker = directory / INCOMPLETE_MARKER
    if marker.exists():
        try:
            info = json.loads(marker.read_text(encoding="utf-8"))
            return (f"incomplete recording ({info.get('reason', 'not finished')}: "
                    f"{int(info.get('frames_written', 0))} of {int(info.get('frames', 0))} frames written); "
                    "record it again")
        except (OSError, ValueError, TypeError, AttributeError, RecursionError):
            return "incomplete recording (interrupted or failed while being written); record it again"
    if (directory / "frames.npy").exists():
        return "incomplete recording (no meta.json: interrupted or failed while being written); record it again"
    return "not a recording (no meta.json)"


def _cell_float(value: str) -> float:
    return float(value) if value.strip() else math.nan


def read_truth(path: Path, n_frames: int) -> Truth:
    """Parse and validate ``truth.csv`` against a recording of ``n_frames`` frames.

    Raises
    ------
    RecordingError
        One line naming the file and line: unreadable or not UTF-8, another
        header, no rows, a cell not a number, a frame out of range or listed
        twice, a contact row without its position, shape, size or depth, an
        unknown shape.
    """
    try:
        if path.stat().st_size > MAX_TRUTH_BYTES:
            raise RecordingError(f"{path}: larger than a truth file can be ({MAX_TRUTH_BYTES >> 20} MiB)")
        with path.open(newline="", encoding="utf-8-sig") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise RecordingError(f"{path}: cannot read truth ({exc})") from None
    if not rows or tuple(c.strip() for c in rows[0]) != TRUTH_HEADER:
        raise RecordingError(f"{path}: header must be '{','.join(TRUTH_HEADER)}'")
    if len(rows) < 2:
        raise RecordingError(f"{path}: no rows after the header")
    cols: list[list[Any]] = [[] for _ in TRUTH_HEADER]
    seen: set[int] = set()
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
        if frame in seen:
            raise RecordingError(f"{path}: line {line_no}: frame {frame} is listed twice")
        seen.add(frame)
        if contact and shape not in SHAPES:
            raise RecordingError(f"{path}: line {line_no}: unknown shape {shape!r}")
        if contact and not all(math.isfinite(v) for i, v in enumerate(values) if TRUTH_HEADER[3 + i] != "angle_deg"):
            missing = [TRUTH_HEADER[3 + i] for i, v in enumerate(values)
                       if not math.isfinite(v) and TRUTH_HEADER[3 + i] != "angle_deg"]
            raise RecordingError(f"{path}: line {line_no}: a contact without {', '.join(missing)}")
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
        if (self.path / INCOMPLETE_MARKER).exists():
            raise RecordingError(f"{self.path}: {_missing_meta(self.path)}")
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
    """Streams frames into a new recording directory; the recording is complete only when closed normally.

    ``frames.npy`` is allocated on disk for ``n_frames`` at the start (a full
    disk fails there, with one line, not with SIGBUS later) and each frame is
    written with ``pwrite``; ``meta.json`` (and ``truth.csv``) are written last,
    on a :meth:`close` after every frame was written. Anything else -- an
    exception or Ctrl-C inside the ``with`` block, :meth:`abort`, a close with
    frames missing -- leaves no ``meta.json`` but ``incomplete.json`` saying
    what happened, and :class:`Recording` refuses the directory in one line.

    Raises
    ------
    OutputError
        If the directory or a file in it cannot be written (full disk, I/O
        error, a target that is not a regular file), naming the file.
    """

    def __init__(
        self,
        path: str | Path,
        n_frames: int,
        frame_shape: tuple[int, ...],
        meta: RecordingMeta,
        with_truth: bool = False,
    ) -> None:
        if n_frames < 1:
            raise ValueError(f"a recording needs at least one frame, got {n_frames}")
        infer_pixel_format(frame_shape)
        self.path = check_output_path(path, directory=True)
        self.meta = meta
        self.n_frames = int(n_frames)
        self.frame_shape = tuple(int(v) for v in frame_shape)
        self._frame_bytes = int(np.prod(self.frame_shape))
        self._truth_rows: list[list[str]] | None = [] if with_truth else None
        self._written = 0
        self._closed = False
        self._fd = -1
        frames_path = self.path / "frames.npy"
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            for stale in ("meta.json", "truth.csv", INCOMPLETE_MARKER):
                (self.path / stale).unlink(missing_ok=True)
            check_output_path(frames_path)
            self._mark_incomplete("being written")
            header = np.lib.format.header_data_from_array_1_0(np.empty((0, *self.frame_shape), np.uint8))
            header["shape"] = (self.n_frames, *self.frame_shape)
            with frames_path.open("wb") as f:
                np.lib.format.write_array_header_1_0(f, header)
                self._offset = f.tell()
            self._fd = os.open(frames_path, os.O_WRONLY)
            size = self._offset + self.n_frames * self._frame_bytes
            try:  # reserve the blocks now: ENOSPC here, not a SIGBUS or a short write later
                os.posix_fallocate(self._fd, 0, size)
            except OSError as exc:
                if exc.errno not in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                    raise
                os.ftruncate(self._fd, size)
        except OSError as exc:
            self._close_fd()
            raise OutputError(f"{frames_path}: {exc.strerror or exc}") from None

    def _mark_incomplete(self, reason: str) -> None:
        (self.path / INCOMPLETE_MARKER).write_text(json.dumps(
            {"reason": reason, "frames_written": self._written, "frames": self.n_frames}) + "\n")

    def _close_fd(self) -> None:
        if self._fd >= 0:
            fd, self._fd = self._fd, -1
            os.close(fd)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: object) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort("interrupted" if issubclass(exc_type, KeyboardInterrupt) else f"failed: {exc}")

    @property
    def frames_written(self) -> int:
        return self._written

    def write(self, index: int, frame: np.ndarray) -> None:
        """Write frame ``index`` (0 .. n_frames-1) of the recording's frame shape, uint8."""
        if not 0 <= index < self.n_frames:
            raise IndexError(f"frame {index} outside 0..{self.n_frames - 1}")
        data = np.ascontiguousarray(frame, dtype=np.uint8)
        if data.shape != self.frame_shape:
            raise FrameMismatchError(f"frame of shape {data.shape}, the recording holds {self.frame_shape}")
        try:
            n = os.pwrite(self._fd, data.data.cast("B"), self._offset + index * self._frame_bytes)
            if n != self._frame_bytes:
                raise OSError(errno.ENOSPC, f"short write ({n} of {self._frame_bytes} bytes)")
        except OSError as exc:
            self.abort(f"failed: {exc.strerror or exc}")
            raise OutputError(f"{self.path / 'frames.npy'}: {exc.strerror or exc}") from None
        self._written = max(self._written, index + 1)

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
        """Complete the recording: every frame written, then truth.csv and meta.json (idempotent).

        Raises
        ------
        RecordingError
            If frames are missing (the recording is left marked incomplete).
        OutputError
            If a file cannot be written.
        """
        if self._closed:
            return
        if self._written < self.n_frames:
            self.abort(f"closed after {self._written} frames")
            raise RecordingError(f"{self.path}: only {self._written} of {self.n_frames} frames were written; "
                                 "the recording is marked incomplete")
        self._closed = True
        try:
            os.fsync(self._fd)
        except OSError as exc:
            self._close_fd()
            self._mark_failed(exc)
            raise OutputError(f"{self.path / 'frames.npy'}: {exc.strerror or exc}") from None
        self._close_fd()
        try:
            if self._truth_rows is not None:
                with AtomicFile(self.path / "truth.csv", "w", newline="") as f:
                    w = csv.writer(f)
                    w.writerow(TRUTH_HEADER)
                    w.writerows(self._truth_rows)
            write_file_atomic(self.path / "meta.json", json.dumps(self.meta.to_json(), indent=2))
        except OutputError as exc:
            self._mark_failed(exc)
            raise
        (self.path / INCOMPLETE_MARKER).unlink(missing_ok=True)
        fsync_directory(self.path)

    def _mark_failed(self, exc: BaseException) -> None:
        try:
            (self.path / "meta.json").unlink(missing_ok=True)
            self._mark_incomplete(f"failed: {exc}")
        except OSError:  # the marker may not fit either: no meta.json is enough
            pass

    def abort(self, reason: str = "aborted") -> None:
        """Stop without completing: no meta.json, ``incomplete.json`` says why (idempotent)."""
        if self._closed:
            return
        self._closed = True
        self._close_fd()
        try:
            self._mark_incomplete(reason)
        except OSError:  # a full disk may refuse even the marker: no meta.json is enough
            pass
