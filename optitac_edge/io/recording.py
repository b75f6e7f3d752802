"""Recordings: a directory of frames plus metadata and optional ground truth.

Layout of a recording directory (a contract; see docs/formats.md):

``frames.npy``  uint8, shape (N, H, W) gray or (N, H, W, 3) RGB; opened
                memory-mapped and streamed, never loaded whole.
``meta.json``   at least ``rest_frames`` (int >= 5, leading contact-free
                frames) and ``fps`` (> 0); other keys are kept as ``extra``.
``truth.csv``   optional, header
                ``frame,contact,shape,x_mm,y_mm,angle_deg,size_mm,depth_mm``,
                optionally followed by ``phase,rig_x_mm,rig_y_mm,rig_z_mm``
                (a rig's pose for every frame, written by ``collect``).
``timestamps.npy`` optional, int64 shape (N,): each frame's capture time,
                CLOCK_MONOTONIC ns (the camera's own where it gives one),
                non-decreasing; without it frame ``i`` is at ``i / fps``.
"""

from __future__ import annotations

import csv
import errno
import io
import json
import math
import os
import shutil
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
#: Optional columns after TRUTH_HEADER: the phase of the press and the rig's pose (rig frame, mm).
RIG_COLUMNS = ("phase", "rig_x_mm", "rig_y_mm", "rig_z_mm")
#: Optional last column: the normal force a load cell measured, N ('' where none).
FORCE_COLUMN = "force_n"
#: Phases of a rig-collected frame; only ``rest`` and ``hold`` frames (and rows without a phase) are scored.
PHASES = ("rest", "approach", "hold", "release", "move")
SCORED_PHASES = ("", "rest", "hold")
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
    #: (N,) float64, N: the load cell's force (NaN where none); None: the recording has no force column.
    force_n: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.frame.shape[0])


@dataclass(frozen=True, eq=False)
class RigPoses:
    """The rig's pose for every row of a rig-collected ``truth.csv``.

    Attributes
    ----------
    frame : ndarray, shape (N,), int64
    phase : ndarray, shape (N,), str
        One of :data:`PHASES`.
    xyz_mm : ndarray, shape (N, 3), float64
        The indenter tip in the rig's coordinates, mm.
    """

    frame: np.ndarray
    phase: np.ndarray
    xyz_mm: np.ndarray


#: Largest truth.csv read, bytes (a row a frame).
MAX_TRUTH_BYTES = 64 << 20
#: Largest meta.json read, bytes (it holds a few numbers and the simulator's parameters).
MAX_META_BYTES = 1 << 20
#: The frame rates a recording may claim, frames/s.
FPS_RANGE = (0.1, 10_000.0)
#: Written instead of meta.json by a writer that did not finish (see RecordingWriter).
INCOMPLETE_MARKER = "incomplete.json"
#: Per-frame capture times, int64 ns.
TIMESTAMPS = "timestamps.npy"
#: The journal of a collection on a rig (``optitac-edge collect``), there until it completes.
COLLECT_JOURNAL = "collect.jsonl"


def read_timestamps(path: Path, n_frames: int) -> np.ndarray:
    """Load and check ``timestamps.npy``: int64, shape (n_frames,), non-decreasing, ns.

    Raises
    ------
    RecordingError
        One line naming the file when it is garbled, of another length or dtype, or goes backwards.
    """
    try:
        t = np.load(path, allow_pickle=False, mmap_mode="r")
    except (OSError, ValueError, EOFError) as exc:
        raise RecordingError(f"{path}: garbled timestamps ({exc})") from None
    if t.dtype != np.int64 or t.shape != (n_frames,):
        raise RecordingError(f"{path}: timestamps must be int64 of shape ({n_frames},), got {t.dtype} {t.shape}")
    t = np.array(t)
    if n_frames > 1 and np.any(np.diff(t) < 0):
        raise RecordingError(f"{path}: timestamps go backwards at frame {int(np.argmax(np.diff(t) < 0)) + 1}")
    return t


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
    return _checked_meta(raw, path)


def _checked_meta(raw: dict[str, Any], path: Path) -> RecordingMeta:
    """A recording's meta from its keys (meta.json's, or an MCAP recording's metadata)."""
    raw = dict(raw)
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
    if marker.exists() and (directory / COLLECT_JOURNAL).exists():
        return ("interrupted collection: run the same 'optitac-edge collect' command to continue it after its "
                "last complete press")
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
    """The scored rows of ``truth.csv`` (see :func:`read_truth_file`)."""
    return read_truth_file(path, n_frames)[0]


def read_truth_file(path: Path, n_frames: int, text: str | None = None) -> tuple[Truth, RigPoses | None]:
    """Parse and validate ``truth.csv`` against a recording of ``n_frames`` frames (``text``: its
    contents, kept elsewhere than ``path``, e.g. in an MCAP recording; ``path`` then names it).

    Returns the truth of the scored rows -- every row, or with the rig columns
    the ``rest`` and ``hold`` frames (during approach and release the depth
    changes within a frame) -- and the rig's pose of every row when present.

    Raises
    ------
    RecordingError
        One line naming the file and line: unreadable or not UTF-8, another
        header, no rows, a cell not a number, a frame out of range or listed
        twice, a contact row without its position, shape, size or depth, an
        unknown shape or phase.
    """
    try:
        if text is not None:
            if len(text) > MAX_TRUTH_BYTES:
                raise RecordingError(f"{path}: larger than a truth file can be ({MAX_TRUTH_BYTES >> 20} MiB)")
            rows = list(csv.reader(io.StringIO(text.removeprefix("\ufeff"), newline="")))
        else:
            if path.stat().st_size > MAX_TRUTH_BYTES:
                raise RecordingError(f"{path}: larger than a truth file can be ({MAX_TRUTH_BYTES >> 20} MiB)")
            with path.open(newline="", encoding="utf-8-sig") as f:
                rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise RecordingError(f"{path}: cannot read truth ({exc})") from None
    header = tuple(c.strip() for c in rows[0]) if rows else ()
    force = bool(header) and header[-1] == FORCE_COLUMN
    base = header[:-1] if force else header
    if base not in (TRUTH_HEADER, TRUTH_HEADER + RIG_COLUMNS):
        raise RecordingError(f"{path}: header must be '{','.join(TRUTH_HEADER)}' "
                             f"(optionally followed by ',{','.join(RIG_COLUMNS)}', then ',{FORCE_COLUMN}')")
    rig = len(base) > len(TRUTH_HEADER)
    if len(rows) < 2:
        raise RecordingError(f"{path}: no rows after the header")
    cols: list[list[Any]] = [[] for _ in TRUTH_HEADER]
    rig_cols: list[list[Any]] = [[], [], []]
    forces: list[float] = []
    seen: set[int] = set()
    n_values = len(TRUTH_HEADER) - 3
    for line_no, row in enumerate(rows[1:], start=2):
        if len(row) != len(header):
            raise RecordingError(f"{path}: line {line_no}: expected {len(header)} cells")
        try:
            frame, contact = int(row[0]), int(row[1])
            values = [_cell_float(c) for c in row[3:3 + n_values]]
            pose = [float(c) for c in row[len(TRUTH_HEADER) + 1:len(base)]]
            force_n = _cell_float(row[-1]) if force else math.nan
        except ValueError:
            raise RecordingError(f"{path}: line {line_no}: not a number") from None
        shape = row[2].strip()
        if not 0 <= frame < n_frames or contact not in (0, 1):
            raise RecordingError(f"{path}: line {line_no}: frame or contact out of range")
        if frame in seen:
            raise RecordingError(f"{path}: line {line_no}: frame {frame} is listed twice")
        seen.add(frame)
        phase = row[len(TRUTH_HEADER)].strip() if rig else ""
        if rig and (phase not in PHASES or not all(math.isfinite(v) for v in pose)):
            raise RecordingError(f"{path}: line {line_no}: unknown phase {phase!r} or a rig pose not finite")
        if contact and shape not in SHAPES:
            raise RecordingError(f"{path}: line {line_no}: unknown shape {shape!r}")
        if contact and not all(math.isfinite(v) for i, v in enumerate(values) if TRUTH_HEADER[3 + i] != "angle_deg"):
            missing = [TRUTH_HEADER[3 + i] for i, v in enumerate(values)
                       if not math.isfinite(v) and TRUTH_HEADER[3 + i] != "angle_deg"]
            raise RecordingError(f"{path}: line {line_no}: a contact without {', '.join(missing)}")
        if force and (math.isinf(force_n) or force_n < 0):
            raise RecordingError(f"{path}: line {line_no}: force_n must be a force >= 0 N or empty")
        if rig:
            rig_cols[0].append(frame)
            rig_cols[1].append(phase)
            rig_cols[2].append(pose)
        if phase not in SCORED_PHASES:
            continue
        for col, value in zip(cols, [frame, bool(contact), shape if contact else "", *values]):
            col.append(value)
        forces.append(force_n)
    truth = Truth(
        frame=np.asarray(cols[0], dtype=np.int64),
        contact=np.asarray(cols[1], dtype=bool),
        shape=np.asarray(cols[2], dtype=str),
        **{name: np.asarray(c, dtype=np.float64) for name, c in zip(TRUTH_HEADER[3:], cols[3:])},
        force_n=np.asarray(forces, dtype=np.float64) if force else None,
    )
    poses = RigPoses(np.asarray(rig_cols[0], dtype=np.int64), np.asarray(rig_cols[1], dtype=str),
                     np.asarray(rig_cols[2], dtype=np.float64).reshape(-1, 3)) if rig else None
    return truth, poses


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
        if self.path.suffix == ".mcap" and self.path.is_file():
            self._open_mcap()
            return
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
        self.truth: Truth | None = None
        #: The rig's pose of every frame, when a rig collected the recording.
        self.rig_poses: RigPoses | None = None
        if truth_path.exists():
            self.truth, self.rig_poses = read_truth_file(truth_path, len(frames))
        stamps = self.path / TIMESTAMPS
        #: True when ``t_ns`` holds the capture times, False when they are nominal (``i / fps``).
        self.timestamped = stamps.exists()
        #: Capture time of each frame, int64 ns, shape (N,).
        self.t_ns: np.ndarray = (read_timestamps(stamps, len(frames)) if self.timestamped else
                                 np.round(np.arange(len(frames)) * (1e9 / self.meta.fps)).astype(np.int64))

    def _open_mcap(self) -> None:
        """A recording in one MCAP file (:mod:`optitac_edge.io.recording_mcap`), with its truth if it holds one."""
        from optitac_edge.io.recording_mcap import read_mcap_recording

        frames, t_ns, raw, truth = read_mcap_recording(self.path)
        self.meta = _checked_meta(raw, self.path)
        self.pixel_format = infer_pixel_format(frames.shape[1:])
        self.frames = frames
        if self.meta.rest_frames > len(frames):
            raise RecordingError(f"{self.path}: rest_frames={self.meta.rest_frames} but only {len(frames)} frames")
        self.truth = None
        self.rig_poses = None
        if truth is not None:
            self.truth, self.rig_poses = read_truth_file(Path(f"{self.path}#truth.csv"), len(frames), text=truth)
        self.timestamped = True
        self.t_ns = t_ns

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


def holds_recording(path: Path) -> bool:
    """``path`` is a complete recording: a directory with ``meta.json``, or an MCAP file."""
    return (path / "meta.json").is_file() if path.is_dir() else path.suffix == ".mcap" and path.is_file()


def staging_path(target: Path) -> Path:
    """Where a recording that replaces ``target`` is written until it is complete: ``TARGET.new``."""
    return target.with_name(target.name + ".new")


def check_writable_recording(path: str | Path, replace: bool) -> Path:
    """``path`` as a Path, refused when it holds a complete recording and ``replace`` is not given.

    The one rule of every recording writer (``sim``, ``record``, ``collect``, directories and MCAP
    files): a complete recording is never overwritten by a run that may not finish.

    Raises
    ------
    OutputError
        One line naming the recording and ``--fresh``.
    """
    target = Path(path)
    if holds_recording(target) and not replace:
        raise OutputError(f"{target}: holds a complete recording; give another output, or --fresh to replace it "
                          "(it is kept until the new one is complete)")
    return target


def swap_in(staging: Path, target: Path) -> None:
    """Put the complete recording ``staging`` in the place of the complete recording ``target``.

    ``target`` is renamed aside first, so at every moment one complete recording is at one of the
    two names, then removed.
    """
    aside = target.with_name(target.name + ".old")
    try:
        shutil.rmtree(aside, ignore_errors=True)
        os.rename(target, aside)
        os.rename(staging, target)
        fsync_directory(target.parent)
    except OSError as exc:
        raise OutputError(f"cannot put {staging} in the place of {target}: {exc.strerror or exc} "
                          f"(the new recording is complete in {staging})") from None
    shutil.rmtree(aside, ignore_errors=True)


#: An open-ended writer grows ``frames.npy`` by this many frames at a time.
GROW_FRAMES = 256
#: Digits reserved in an open-ended ``frames.npy`` header for the frame count.
_COUNT_DIGITS = 15


def _npy_header(shape: tuple[int, ...], length: int | None = None) -> bytes:
    """A ``.npy`` v1.0 header of uint8 ``shape``, padded to ``length`` bytes (else to a multiple of 64)."""
    text = f"{{'descr': '|u1', 'fortran_order': False, 'shape': {shape!r}, }}"
    total = length if length is not None else -(-(10 + len(text) + 1) // 64) * 64
    pad = total - 10 - len(text) - 1
    if pad < 0:
        raise ValueError("header does not fit")
    body = (text + " " * pad + "\n").encode("latin1")
    return b"\x93NUMPY\x01\x00" + len(body).to_bytes(2, "little") + body


class RecordingWriter:
    """Streams frames into a new recording directory; the recording is complete only when closed normally.

    ``frames.npy`` is allocated on disk for ``n_frames`` at the start (a full
    disk fails there, with one line, not with SIGBUS later) and each frame is
    written with ``pwrite``; ``meta.json`` (and ``truth.csv``,
    ``timestamps.npy``) are written last, on a :meth:`close` after every frame
    was written. Anything else -- an exception or Ctrl-C inside the ``with``
    block, :meth:`abort`, a close with frames missing -- leaves no
    ``meta.json`` but ``incomplete.json`` saying what happened, and
    :class:`Recording` refuses the directory in one line.

    Parameters
    ----------
    n_frames : int or None
        Frames the recording will hold; ``None``: open-ended, the file grows
        ``GROW_FRAMES`` at a time and holds the frames written when closed
        (frames ``0 .. k-1`` without gaps).
    with_truth : bool
        Collect ``truth.csv`` rows (:meth:`write_truth`).
    rig_columns : bool
        ``truth.csv`` carries the rig's phase and pose (:data:`RIG_COLUMNS`).
    force_column : bool
        ``truth.csv`` carries a load cell's force (:data:`FORCE_COLUMN`, last).
    keep_frames : int
        Open-ended only: continue an existing incomplete recording of this
        frame shape after its first ``keep_frames`` frames (their times in
        ``kept_t_ns``, their truth rows given again with :meth:`write_truth`).
        The frames written from then on are a new *segment*: their clock may
        have restarted (a reboot restarts CLOCK_MONOTONIC; the simulator's
        virtual clock starts at 0 in every process), so when the first new
        time is not after the last kept one, every new time is shifted to
        follow it by one frame period. ``meta.json`` lists the segments
        (``segments``: first frame and the shift, ns), :attr:`segments`.
    kept_segments : list of dict, optional
        The segments of the kept frames (default: one, from frame 0, unshifted).
    replace : bool
        ``path`` may hold a complete recording: it is replaced when this one
        is complete (written beside it as ``PATH.new`` until then), never
        before. Without ``replace`` a complete recording is refused.

    Raises
    ------
    OutputError
        If the directory or a file in it cannot be written (full disk, I/O
        error, a target that is not a regular file), naming the file; if
        ``path`` holds a complete recording and ``replace`` is not given.
    RecordingError
        If ``keep_frames`` asks for frames the existing recording does not hold.
    """

    def __init__(
        self,
        path: str | Path,
        n_frames: int | None,
        frame_shape: tuple[int, ...],
        meta: RecordingMeta,
        with_truth: bool = False,
        rig_columns: bool = False,
        keep_frames: int = 0,
        kept_t_ns: np.ndarray | None = None,
        force_column: bool = False,
        kept_segments: list[dict[str, int]] | None = None,
        replace: bool = False,
    ) -> None:
        if n_frames is not None and n_frames < 1:
            raise ValueError(f"a recording needs at least one frame, got {n_frames}")
        if keep_frames and n_frames is not None:
            raise ValueError("only an open-ended recording can be continued")
        infer_pixel_format(frame_shape)
        #: Where the recording will be once complete; :attr:`path` is where it is written until then.
        self.target = check_writable_recording(path, replace)
        self.replacing = holds_recording(self.target)
        self.path = staging_path(self.target) if self.replacing else self.target
        if self.replacing:
            check_output_path(self.path, directory=True)
            shutil.rmtree(self.path, ignore_errors=True)  # an earlier replacement that did not complete
        self.meta = meta
        #: The segments written with one clock each: ``{"first_frame": i, "offset_ns": shift}``.
        self.segments: list[dict[str, int]] = [dict(s) for s in kept_segments] if kept_segments else [
            {"first_frame": 0, "offset_ns": 0}]
        self._new_segment = bool(keep_frames)
        self._shift_ns = 0 if keep_frames else self.segments[-1]["offset_ns"]
        self._period_ns = max(1, round(1e9 / meta.fps))
        self.open_ended = n_frames is None
        self.n_frames = GROW_FRAMES if n_frames is None else int(n_frames)
        self.frame_shape = tuple(int(v) for v in frame_shape)
        self._frame_bytes = int(np.prod(self.frame_shape))
        self._truth_rows: list[list[str]] | None = [] if with_truth or rig_columns or force_column else None
        self._rig = rig_columns
        self._force = force_column
        self._written = 0
        self._closed = False
        self._fd = -1
        self._t_ns = np.zeros(self.n_frames, dtype=np.int64)
        self._stamped = np.zeros(self.n_frames, dtype=bool)
        frames_path = self.path / "frames.npy"
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            for stale in ("meta.json", "truth.csv", TIMESTAMPS):
                (self.path / stale).unlink(missing_ok=True)
            check_output_path(frames_path)
            if keep_frames:
                self._continue(frames_path, keep_frames, kept_t_ns)
            else:
                (self.path / INCOMPLETE_MARKER).unlink(missing_ok=True)
                self._mark_incomplete("being written")
                shape = (10**_COUNT_DIGITS - 1 if self.open_ended else self.n_frames, *self.frame_shape)
                with frames_path.open("wb") as f:
                    f.write(_npy_header(shape))
                    self._offset = f.tell()
                self._fd = os.open(frames_path, os.O_WRONLY)
                self._reserve(self.n_frames)
        except OSError as exc:
            self._close_fd()
            raise OutputError(f"{frames_path}: {exc.strerror or exc}") from None

    def _continue(self, frames_path: Path, keep: int, kept_t_ns: np.ndarray | None) -> None:
        """Reopen an incomplete open-ended recording, keeping its first ``keep`` frames."""
        try:
            with frames_path.open("rb") as f:
                if np.lib.format.read_magic(f) != (1, 0):
                    raise ValueError("not written by this writer")
                shape, _, dtype = np.lib.format.read_array_header_1_0(f)
                offset = f.tell()
            size = frames_path.stat().st_size
        except (OSError, ValueError) as exc:
            raise RecordingError(f"{frames_path}: cannot continue this recording ({exc})") from None
        if (dtype != np.uint8 or tuple(shape[1:]) != self.frame_shape
                or size < offset + keep * self._frame_bytes):
            raise RecordingError(f"{frames_path}: cannot continue this recording (it holds other frames, "
                                 f"or fewer than {keep})")
        if kept_t_ns is None or len(kept_t_ns) != keep:
            raise ValueError("keep_frames needs the kept frames' times")
        self._mark_incomplete("being written")
        self._offset = offset
        self._fd = os.open(frames_path, os.O_WRONLY)
        self._grow_to(keep + GROW_FRAMES)
        self._t_ns[:keep] = kept_t_ns
        self._stamped[:keep] = True
        self._written = keep

    def _reserve(self, n_frames: int) -> None:
        """Allocate the blocks of ``n_frames`` frames now: ENOSPC here, not a SIGBUS or a short write later."""
        size = self._offset + n_frames * self._frame_bytes
        try:
            os.posix_fallocate(self._fd, 0, size)
        except OSError as exc:
            if exc.errno not in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                raise
            os.ftruncate(self._fd, size)

    def _grow_to(self, n_frames: int) -> None:
        """Room for ``n_frames`` (more than today) on disk and in the frame times."""
        self._reserve(n_frames)
        extra = n_frames - self.n_frames
        self._t_ns = np.concatenate([self._t_ns, np.zeros(extra, np.int64)])
        self._stamped = np.concatenate([self._stamped, np.zeros(extra, bool)])
        self.n_frames = n_frames

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

    def write(self, index: int, frame: np.ndarray, t_ns: int | None = None) -> int | None:
        """Write frame ``index`` (0 .. n_frames-1; open-ended: any) of the recording's frame shape, uint8.

        ``t_ns`` is the frame's capture time (ns); when every frame has one they
        are saved in ``timestamps.npy``, else frames are at ``i / fps``. Returns
        the time saved (``t_ns`` shifted as its segment is, see ``keep_frames``).
        """
        if index < 0 or (index >= self.n_frames and not self.open_ended):
            raise IndexError(f"frame {index} outside 0..{self.n_frames - 1}")
        data = np.ascontiguousarray(frame, dtype=np.uint8)
        if data.shape != self.frame_shape:
            raise FrameMismatchError(f"frame of shape {data.shape}, the recording holds {self.frame_shape}")
        try:
            if index >= self.n_frames:
                self._grow_to(max(index + 1, self.n_frames + GROW_FRAMES))
            n = os.pwrite(self._fd, data.data.cast("B"), self._offset + index * self._frame_bytes)
            if n != self._frame_bytes:
                raise OSError(errno.ENOSPC, f"short write ({n} of {self._frame_bytes} bytes)")
        except OSError as exc:
            self.abort(f"failed: {exc.strerror or exc}")
            raise OutputError(f"{self.path / 'frames.npy'}: {exc.strerror or exc}") from None
        self._written = max(self._written, index + 1)
        if t_ns is None:
            return None
        if self._new_segment:  # the first frame after continuing: does its clock follow the kept frames'?
            self._new_segment = False
            last = int(self._t_ns[index - 1]) if index > 0 and self._stamped[index - 1] else None
            self._shift_ns = 0 if last is None or t_ns > last else last + self._period_ns - int(t_ns)
            self.segments.append({"first_frame": index, "offset_ns": self._shift_ns})
        stamped = int(t_ns) + self._shift_ns
        self._t_ns[index] = stamped
        self._stamped[index] = True
        return stamped

    def sync(self) -> None:
        """Make every frame written so far durable (before a journal says they are there)."""
        try:
            os.fsync(self._fd)
        except OSError as exc:
            self.abort(f"failed: {exc.strerror or exc}")
            raise OutputError(f"{self.path / 'frames.npy'}: {exc.strerror or exc}") from None

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
        phase: str = "",
        rig_xyz_mm: tuple[float, float, float] | None = None,
        force_n: float = math.nan,
    ) -> None:
        """Add the truth row of ``frame``; with ``rig_columns`` also its ``phase`` and the rig's pose,
        with ``force_column`` the force (N; NaN: none)."""
        if self._truth_rows is None:
            raise ValueError("writer was opened without truth")
        if self._rig and (phase not in PHASES or rig_xyz_mm is None):
            raise ValueError(f"a rig row needs a phase in {PHASES} and the rig's pose")

        def cell(v: float) -> str:
            return "" if not contact or math.isnan(v) else f"{v:.4f}"

        row = [str(frame), str(int(contact)), shape if contact else "",
               *(cell(v) for v in (x_mm, y_mm, angle_deg, size_mm, depth_mm))]
        if self._rig and rig_xyz_mm is not None:
            row += [phase, *(f"{v:.4f}" for v in rig_xyz_mm)]
        if self._force:
            row.append("" if math.isnan(force_n) else f"{force_n:.4f}")
        self._truth_rows.append(row)

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
        if self.open_ended:
            self.n_frames = self._written
        if self._written < self.n_frames or self._written == 0:
            self.abort(f"closed after {self._written} frames")
            raise RecordingError(f"{self.path}: only {self._written} of {self.n_frames} frames were written; "
                                 "the recording is marked incomplete")
        self._closed = True
        try:
            if self.open_ended:
                os.ftruncate(self._fd, self._offset + self._written * self._frame_bytes)
                header = _npy_header((self._written, *self.frame_shape), self._offset)
                if os.pwrite(self._fd, header, 0) != len(header):
                    raise OSError(errno.EIO, "short write of the header")
            os.fsync(self._fd)
        except OSError as exc:
            self._close_fd()
            self._mark_failed(exc)
            raise OutputError(f"{self.path / 'frames.npy'}: {exc.strerror or exc}") from None
        self._close_fd()
        try:
            stamped = self._stamped[: self._written]
            if stamped.all():
                t = self._t_ns[: self._written]
                if np.any(np.diff(t) < 0):
                    raise OutputError(f"{self.path / TIMESTAMPS}: frame times go backwards")
                with AtomicFile(self.path / TIMESTAMPS, "wb") as f:
                    np.save(f, t, allow_pickle=False)
            if self._truth_rows is not None:
                with AtomicFile(self.path / "truth.csv", "w", newline="") as f:
                    w = csv.writer(f)
                    w.writerow(TRUTH_HEADER + (RIG_COLUMNS if self._rig else ())
                               + ((FORCE_COLUMN,) if self._force else ()))
                    w.writerows(self._truth_rows)
            meta = self.meta.to_json()
            if len(self.segments) > 1:
                meta["segments"] = self.segments
            write_file_atomic(self.path / "meta.json", json.dumps(meta, indent=2))
        except OutputError as exc:
            self._mark_failed(exc)
            raise
        (self.path / INCOMPLETE_MARKER).unlink(missing_ok=True)
        fsync_directory(self.path)
        if self.replacing:
            swap_in(self.path, self.target)

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
