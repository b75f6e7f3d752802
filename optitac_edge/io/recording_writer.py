"""Writing a recording directory: frames (raw or as fiber sums), times, truth and meta, all or nothing.

One rule for every writer (:mod:`optitac_edge.io.recording_paths`): a complete
recording is never overwritten by a run that may not finish.
"""

from __future__ import annotations

import csv
import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from optitac_edge.core.frames import infer_pixel_format
from optitac_edge.errors import FrameMismatchError, OutputError, RecordingError
from optitac_edge.io.files import AtomicFile, check_output_path, fsync_directory, write_file_atomic
from optitac_edge.io.frame_store import (
    COLOURS,
    RAW_FRAMES,
    REST_FRAMES,
    SPOTS,
    SUMS,
    FiberSumStore,
    FindFibers,
    FrameStore,
    RawFrameStore,
)
from optitac_edge.io.recording import (
    FORCE_COLUMN,
    INCOMPLETE_MARKER,
    MOTION_COLUMNS,
    PHASES,
    RIG_COLUMNS,
    TIMESTAMPS,
    TRUTH_HEADER,
    RecordingMeta,
)
from optitac_edge.io.recording_paths import check_writable_recording, holds_recording, staging_path, swap_in
from optitac_edge.io.recording_rate import state_rate_shown

if TYPE_CHECKING:
    from typing_extensions import Self

#: The frame times are kept in memory this many at a time more (open-ended writers).
_GROW_TIMES = 4096


class PressTruth(Protocol):
    """What a truth row says of a press, in the sensor's frame (the simulator's ``Indenter`` has it, as
    :class:`Press` does)."""

    @property
    def shape(self) -> str: ...
    @property
    def x_mm(self) -> float: ...
    @property
    def y_mm(self) -> float: ...
    @property
    def angle_deg(self) -> float: ...
    @property
    def size_mm(self) -> float: ...
    @property
    def depth_mm(self) -> float: ...


@dataclass(frozen=True)
class Press:
    """A press's truth: shape, centre (mm), angle (degrees; NaN: none), size and depth (mm)."""

    shape: str
    x_mm: float
    y_mm: float
    angle_deg: float
    size_mm: float
    depth_mm: float


class RecordingWriter:
    """Streams frames into a new recording directory; the recording is complete only when closed normally.

    The frames go to a :class:`~optitac_edge.io.frame_store.FrameStore` (``storage``: ``raw`` frames, or
    ``fibers``: the rest frames as they are and each fiber's light for the rest), with ``pwrite`` into space
    allocated ahead; ``meta.json`` (and ``truth.csv``, ``timestamps.npy``) are written last, on a
    :meth:`close` after every frame was written. Anything else -- an exception or Ctrl-C inside the
    ``with`` block, :meth:`abort`, a close with frames missing -- leaves no ``meta.json`` but
    ``incomplete.json`` saying what happened, and :class:`~optitac_edge.io.recording.Recording` refuses the
    directory in one line.

    Parameters
    ----------
    path : path-like
        The recording directory.
    n_frames : int or None
        Frames the recording will hold; ``None``: open-ended, it holds the frames written when closed
        (frames ``0 .. k-1`` without gaps).
    frame_shape : tuple of int
    meta : RecordingMeta
    with_truth : bool
        Collect ``truth.csv`` rows (:meth:`write_truth`).
    rig_columns : bool
        ``truth.csv`` carries the rig's phase and pose (:data:`~optitac_edge.io.recording.RIG_COLUMNS`).
    keep_frames : int
        Open-ended only: continue an existing incomplete recording of this frame shape and storage after
        its first ``keep_frames`` frames (their times in ``kept_t_ns``, their truth rows given again with
        :meth:`write_truth`). The frames written from then on are a new *segment*: their clock may have
        restarted (a reboot restarts CLOCK_MONOTONIC; the simulator's virtual clock starts at 0 in every
        process), so when the first new time is not after the last kept one, every new time is shifted to
        follow it by one frame period. ``meta.json`` lists the segments (``segments``: first frame and the
        shift, ns), :attr:`segments`.
    force_column : bool
        ``truth.csv`` carries a load cell's force (:data:`~optitac_edge.io.recording.FORCE_COLUMN`, last).
    motion_columns : bool
        ``truth.csv`` carries the press's true velocity and motion
        (:data:`~optitac_edge.io.recording.MOTION_COLUMNS`, before the force).
    kept_segments : list of dict, optional
        The segments of the kept frames (default: one, from frame 0, unshifted).
    replace : bool
        ``path`` may hold a complete recording: it is replaced when this one is complete (written beside it
        as ``PATH.new`` until then), never before. Without ``replace`` a complete recording is refused.
    storage : {"raw", "fibers"}
        How the frames are kept (:mod:`optitac_edge.io.frame_store`).
    find_fibers : callable, optional
        ``fibers`` storage: finds the fibers in the rest frames (e.g.
        :func:`~optitac_edge.calibration.fibers.calibrate_fibers`'s table).

    Raises
    ------
    OutputError
        If the directory or a file in it cannot be written (full disk, I/O error, a target that is not a
        regular file), naming the file; if ``path`` holds a complete recording and ``replace`` is not given.
    RecordingError
        If ``keep_frames`` asks for frames the existing recording does not hold, or in another storage.
    """

    def __init__(  # noqa: PLR0913
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
        storage: str = "raw",
        find_fibers: FindFibers | None = None,
        motion_columns: bool = False,
    ) -> None:
        if n_frames is not None and n_frames < 1:
            raise ValueError(f"a recording needs at least one frame, got {n_frames}")
        if keep_frames and n_frames is not None:
            raise ValueError("only an open-ended recording can be continued")
        if storage == "fibers" and find_fibers is None:
            raise ValueError("fiber sums need a way to find the fibers (find_fibers)")
        if keep_frames and (kept_t_ns is None or len(kept_t_ns) != keep_frames):
            raise ValueError("keep_frames needs the kept frames' times")
        infer_pixel_format(frame_shape)
        #: Where the recording will be once complete; :attr:`path` is where it is written until then.
        self.target = check_writable_recording(path, replace)
        self.replacing = holds_recording(self.target)
        self.path = staging_path(self.target) if self.replacing else self.target
        self.meta = meta
        #: The segments written with one clock each: ``{"first_frame": i, "offset_ns": shift}``.
        self.segments: list[dict[str, int]] = [dict(s) for s in kept_segments] if kept_segments else [
            {"first_frame": 0, "offset_ns": 0}]
        self._new_segment = bool(keep_frames)
        self._shift_ns = 0 if keep_frames else self.segments[-1]["offset_ns"]
        self._period_ns = max(1, round(1e9 / meta.fps))
        self.open_ended = n_frames is None
        self.n_frames = n_frames
        self.frame_shape = tuple(int(v) for v in frame_shape)
        self._truth_rows: list[list[str]] | None = ([] if with_truth or rig_columns or force_column or motion_columns
                                                    else None)
        self._motion = motion_columns
        self._rig = rig_columns
        self._force = force_column
        self._written = 0
        self._closed = False
        size = n_frames if n_frames is not None else keep_frames + _GROW_TIMES
        self._t_ns = np.zeros(size, dtype=np.int64)
        self._stamped = np.zeros(size, dtype=bool)
        self._store: FrameStore | None = self._open_store(keep_frames, storage, find_fibers)
        if keep_frames:
            assert kept_t_ns is not None
            self._t_ns[:keep_frames] = kept_t_ns
            self._stamped[:keep_frames] = True

    def _open_store(self, keep_frames: int, storage: str, find_fibers: FindFibers | None) -> FrameStore:
        """Make the directory ready (an earlier replacement's leftovers and stale files gone, marked
        incomplete) and open its frame store, keeping ``keep_frames`` frames of an interrupted recording."""
        try:
            if self.replacing:
                check_output_path(self.path, directory=True)
                shutil.rmtree(self.path, ignore_errors=True)  # an earlier replacement that did not complete
            check_output_path(self.path, directory=True)
            self.path.mkdir(parents=True, exist_ok=True)
            for stale in ("meta.json", "truth.csv", TIMESTAMPS):
                (self.path / stale).unlink(missing_ok=True)
            if not keep_frames:
                for stale in (INCOMPLETE_MARKER, RAW_FRAMES, REST_FRAMES, SPOTS, SUMS, COLOURS):
                    (self.path / stale).unlink(missing_ok=True)
            self._written = keep_frames
            self._mark_incomplete("being written")
            if storage == "fibers":
                assert find_fibers is not None
                return FiberSumStore(self.path, self.frame_shape, self.meta.rest_frames, find_fibers,
                                     keep_frames=keep_frames)
            if storage == "raw":
                return RawFrameStore(self.path, self.frame_shape, self.n_frames, keep_frames=keep_frames)
            raise ValueError(f"unknown storage {storage!r}")
        except OSError as exc:
            raise OutputError(f"{self.path}: {exc.strerror or exc}") from None

    def _mark_incomplete(self, reason: str) -> None:
        (self.path / INCOMPLETE_MARKER).write_text(json.dumps(
            {"reason": reason, "frames_written": self._written,
             "frames": self._written if self.n_frames is None else self.n_frames}) + "\n")

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
        """Write frame ``index`` (0 .. n_frames-1; open-ended: any, ``fibers``: in order) of the recording's
        frame shape, uint8.

        ``t_ns`` is the frame's capture time (ns); when every frame has one they are saved in
        ``timestamps.npy``, else frames are at ``i / fps``. Returns the time saved (``t_ns`` shifted as its
        segment is, see ``keep_frames``).
        """
        if index < 0 or (self.n_frames is not None and index >= self.n_frames):
            raise IndexError(f"frame {index} outside 0..{(self.n_frames or 0) - 1}")
        data = np.ascontiguousarray(frame, dtype=np.uint8)
        if data.shape != self.frame_shape:
            raise FrameMismatchError(f"frame of shape {data.shape}, the recording holds {self.frame_shape}")
        assert self._store is not None
        try:
            self._store.write(index, data)
        except OutputError as exc:
            self.abort(f"failed: {exc}")
            raise
        self._written = max(self._written, index + 1)
        if t_ns is None:
            return None
        if index >= self._t_ns.size:
            extra = max(index + 1, self._t_ns.size + _GROW_TIMES) - self._t_ns.size
            self._t_ns = np.concatenate([self._t_ns, np.zeros(extra, np.int64)])
            self._stamped = np.concatenate([self._stamped, np.zeros(extra, bool)])
        if self._new_segment:  # the first frame after continuing: does its clock follow the kept frames'?
            self._new_segment = False
            last = int(self._t_ns[index - 1]) if index > 0 and self._stamped[index - 1] else None
            self._shift_ns = 0 if last is None or t_ns > last else last + self._period_ns - int(t_ns)
            self.segments.append({"first_frame": index, "offset_ns": self._shift_ns})
        stamped = int(t_ns) + self._shift_ns
        if not 0 <= stamped < 2**63:
            raise OutputError(f"{self.target}: frame {index}'s time {t_ns} ns (shifted by {self._shift_ns} ns) is "
                              "not a time this recording can hold (0..2^63 ns)")
        self._t_ns[index] = stamped
        self._stamped[index] = True
        return stamped

    def sync(self) -> None:
        """Make every frame written so far durable (before a journal says they are there)."""
        assert self._store is not None
        try:
            self._store.sync()
        except OutputError as exc:
            self.abort(f"failed: {exc}")
            raise

    def write_truth(self, frame: int, press: PressTruth | None, phase: str = "",
                    rig_xyz_mm: tuple[float, float, float] | None = None, force_n: float = math.nan,
                    motion: tuple[float, float, str] = (math.nan, math.nan, "")) -> None:
        """Add the truth row of ``frame``: the ``press`` on it (None: no contact); with ``rig_columns`` also its
        ``phase`` and the rig's pose, with ``motion_columns`` its velocity (mm/s) and motion (one of
        :data:`~optitac_edge.io.recording.MOTION_STATES`, '' without contact), with ``force_column`` the
        force (N; NaN: none)."""
        if self._truth_rows is None:
            raise ValueError("writer was opened without truth")
        if self._rig and (phase not in PHASES or rig_xyz_mm is None):
            raise ValueError(f"a rig row needs a phase in {PHASES} and the rig's pose")

        def cell(v: float) -> str:
            return "" if math.isnan(v) else f"{v:.4f}"

        row = [str(frame), "0", "", "", "", "", "", ""] if press is None else [
            str(frame), "1", press.shape,
            *(cell(v) for v in (press.x_mm, press.y_mm, press.angle_deg, press.size_mm, press.depth_mm))]
        if self._rig and rig_xyz_mm is not None:
            row += [phase, *(f"{v:.4f}" for v in rig_xyz_mm)]
        if self._motion:
            row += [cell(motion[0]), cell(motion[1]), motion[2]]
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
        expected = self._written if self.n_frames is None else self.n_frames
        if self._written < expected or self._written == 0:
            self.abort(f"closed after {self._written} frames")
            raise RecordingError(f"{self.path}: only {self._written} of {expected} frames were written; "
                                 "the recording is marked incomplete")
        self._closed = True
        assert self._store is not None
        try:
            storage = self._store.finish(self._written)
        except (OutputError, RecordingError) as exc:
            self._store.close()
            self._mark_failed(exc)
            raise
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
                               + (MOTION_COLUMNS if self._motion else ()) + ((FORCE_COLUMN,) if self._force else ()))
                    w.writerows(self._truth_rows)
            meta = self.meta.to_json()
            if stamped.all():
                state_rate_shown(meta, self._t_ns[: self._written], self.target)
            if len(self.segments) > 1:
                meta["segments"] = self.segments
            if storage:
                meta["frame_storage"] = storage
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
        if self._store is not None:
            self._store.close()
        try:
            self._mark_incomplete(reason)
        except OSError:  # a full disk may refuse even the marker: no meta.json is enough
            pass
