"""How a recording keeps its frames on disk: raw, or compact as each fiber's light (the default of a rig).

``raw``
    ``frames.npy``: every frame as the camera gave it (uint8, (N, H, W) or
    (N, H, W, 3)). About 300 kB a frame at 640x480: 70 MB/s at 240 fps, which
    no SD card sustains, and 5 GB for a ``seen`` collection.

``fibers``
    ``rest.npy``: the recording's rest frames as they are, so the fiber map can
    be found again from them; ``spots.npz``: the pixels of every fiber found in
    those rest frames (the fiber map's pixel groups, the same
    :func:`~optitac_edge.calibration.fibers.calibrate_fibers` finds there);
    ``sums.npy``: for every later frame, the sum of each fiber's gray levels
    (uint16, 434 bytes a frame for 217 fibers: 100 kB/s at 240 fps);
    ``colours.npy``, RGB recordings only: for every later frame the sums of
    each fiber's red, green and blue levels (N x 3, the same integer type: 1.3 kB
    a frame for 217 fibers), each fiber's colour kept for a colour mix and for
    later shear and torsion from colour. The
    per-frame loop reads nothing of a frame but those pixels, so a bundle
    whose fiber map is the recording's own sees exactly the fiber light it
    would see in the raw frames (:mod:`optitac_edge.io.fiber_sums` gives the
    frames back). The fibers are found in a thread while the frames after the
    rest wait in memory, so the camera is not held up.

Both write with ``pwrite`` into space allocated ahead (:class:`~optitac_edge.io.npy_rows.NpyRows`).
"""

from __future__ import annotations

import io
import logging
import threading
import zipfile
from abc import ABC, abstractmethod
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from optitac_edge.core.fiber_table import FiberSampler, FiberTable
from optitac_edge.core.frames import infer_pixel_format
from optitac_edge.errors import FrameMismatchError, OutputError, RecordingError
from optitac_edge.io.files import AtomicFile
from optitac_edge.io.npy_rows import NpyRows, npy_shape
from optitac_edge.io.npz_members import NpzLimits, read_npz_members

log = logging.getLogger(__name__)

#: The storages a recording's frames may be in.
STORAGES = ("fibers", "raw")
RAW_FRAMES = "frames.npy"
REST_FRAMES = "rest.npy"
SPOTS = "spots.npz"
SUMS = "sums.npy"
COLOURS = "colours.npy"
#: Frames waiting in memory for the fiber map before the writer waits for it instead, bytes.
PENDING_BYTES = 256 << 20

#: Finds the fibers in rest frames ((K, H, W[, 3]) uint8) of a pixel format: a table whose pixel groups are kept.
FindFibers = Callable[[np.ndarray, str], FiberTable]


#: What ``spots.npz`` holds, as the writer writes it: name -> (dtype kind, dtype) (no array is cast on reading).
_SPOT_ARRAYS = {"pixel_index": np.int32, "pixel_start": np.int64, "centroid_px": np.float64, "dead": np.bool_}


#: What ``spots.npz`` may hold (read with its sizes checked first: a 1.2 MB file inflating to 1.2 GB took
#: 2.4 GB of memory before it was refused); a 4096 x 4096 frame's pixel groups take 64 MiB.
_SPOT_LIMITS = NpzLimits("recording's fiber pixel groups", 256 << 20, 512 << 20, 16)


def read_spots(path: Path, frame_shape: tuple[int, ...]) -> FiberTable:
    """The fiber pixel groups a recording's sums are over (``spots.npz``), checked.

    Each array must have the type the writer gives it (nothing is cast: a float or 64-bit index is refused),
    the groups must start at 0, each own a pixel, end at the last index, lie in the frame and share no pixel.

    Raises
    ------
    RecordingError
        Naming the file, when it is garbled or does not fit the frames.
    """
    try:
        members = read_npz_members(path, _SPOT_LIMITS, RecordingError)
        arrays = {k: members[k] for k in _SPOT_ARRAYS}
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as exc:
        raise RecordingError(f"{path}: garbled fiber pixel groups ({exc})") from None
    for name, dtype in _SPOT_ARRAYS.items():
        if arrays[name].dtype != dtype:
            raise RecordingError(f"{path}: {name} must be {np.dtype(dtype)}, got {arrays[name].dtype}")
    index, start = arrays["pixel_index"], arrays["pixel_start"]
    h, w = (int(v) for v in frame_shape[:2])
    n = start.size - 1
    if index.ndim != 1 or start.ndim != 1 or n < 1 or arrays["centroid_px"].shape != (n, 2) \
            or arrays["dead"].shape != (n,):
        raise RecordingError(f"{path}: arrays of shapes that do not fit one another")
    if start[0] != 0 or start[-1] != index.size or np.any(np.diff(start) < 1):
        raise RecordingError(f"{path}: pixel groups that do not start at 0, own a pixel each and end at the last "
                             "index")
    if index.size and (index.min() < 0 or index.max() >= h * w):
        raise RecordingError(f"{path}: pixel indices outside the {h}x{w} frame")
    if np.unique(index).size != index.size:
        raise RecordingError(f"{path}: pixel groups that share pixels (a pixel belongs to one fiber)")
    try:
        return FiberTable(height=h, width=w, pixel_format=infer_pixel_format(frame_shape), pixel_index=index,
                          pixel_start=start, centroid_px=arrays["centroid_px"], dead=arrays["dead"],
                          unmatched_px=np.zeros((0, 2)))
    except (ValueError, TypeError, FrameMismatchError) as exc:
        raise RecordingError(f"{path}: garbled fiber pixel groups ({exc})") from None


def _size(shape: tuple[int, ...] | None) -> str:
    """``480x640`` (``x3`` for RGB) for a line a person reads."""
    return "unknown size" if shape is None else "x".join(str(v) for v in shape)


class FrameStore(ABC):
    """Where a recording writer puts its frames. Errors are :class:`OutputError` naming the file."""

    #: The storage's name (:data:`STORAGES`).
    storage: str

    @abstractmethod
    def write(self, index: int, frame: np.ndarray) -> None:
        """Frame ``index``."""

    @abstractmethod
    def sync(self) -> None:
        """Every frame written so far onto the disk."""

    @abstractmethod
    def finish(self, n_frames: int) -> dict[str, Any]:
        """The store holds frames ``0 .. n_frames - 1``, synced; what ``meta.json`` says of it."""

    @abstractmethod
    def close(self) -> None:
        """Release the files (idempotent); what was written stays."""


class RawFrameStore(FrameStore):
    """``frames.npy``, every frame as it is.

    Parameters
    ----------
    directory : Path
    frame_shape : tuple of int
    n_frames : int or None
        None: open-ended.
    keep_frames : int
        Continue an open-ended store after its first ``keep_frames`` frames.
    """

    storage = "raw"

    def __init__(self, directory: Path, frame_shape: tuple[int, ...], n_frames: int | None,
                 keep_frames: int = 0) -> None:
        path = directory / RAW_FRAMES
        if keep_frames and not path.exists():
            raise RecordingError(f"{directory}: holds no raw frames to continue (collected with --storage "
                                 "fibers? continue it with the same storage)")
        self._rows = NpyRows(path, frame_shape, np.uint8, n_frames, keep_rows=keep_frames)

    def write(self, index: int, frame: np.ndarray) -> None:
        self._rows.write(index, frame)

    def sync(self) -> None:
        self._rows.sync()

    def finish(self, n_frames: int) -> dict[str, Any]:
        self._rows.finish(n_frames)
        return {}

    def close(self) -> None:
        self._rows.close()


class FiberSumStore(FrameStore):
    """``rest.npy``, ``spots.npz`` and ``sums.npy`` (see the module docstring). Frames are written in order.

    Parameters
    ----------
    directory : Path
    frame_shape : tuple of int
    rest_frames : int
        The recording's leading rest frames, kept as they are.
    find_fibers : callable
        Finds the fibers in the rest frames (run in a thread of its own).
    keep_frames : int
        Continue a store after its first ``keep_frames`` frames (at least the rest frames).
    """

    storage = "fibers"

    def __init__(self, directory: Path, frame_shape: tuple[int, ...], rest_frames: int, find_fibers: FindFibers,
                 keep_frames: int = 0) -> None:
        self.directory = directory
        self.frame_shape = tuple(int(v) for v in frame_shape)
        self.pixel_format = infer_pixel_format(self.frame_shape)
        self.rest_frames = rest_frames
        self._find_fibers = find_fibers
        self._written = keep_frames
        self._rest_copies: list[np.ndarray] = []
        self._pending: list[tuple[int, np.ndarray]] = []
        self._finder: threading.Thread | None = None
        self._found: FiberTable | BaseException | None = None
        self._sampler: FiberSampler | None = None
        self._sums: NpyRows | None = None
        self._colours: NpyRows | None = None
        self._rest: NpyRows | None = None
        if keep_frames:
            self._resume(keep_frames)
        else:
            self._rest = NpyRows(directory / REST_FRAMES, self.frame_shape, np.uint8, rest_frames)

    def _resume(self, keep: int) -> None:
        if keep < self.rest_frames or not (self.directory / SPOTS).exists():
            raise RecordingError(f"{self.directory}: holds no fiber sums to continue after frame {keep} (collected "
                                 "with --storage raw? continue it with the same storage)")
        stated = npy_shape(self.directory / REST_FRAMES)
        kept_shape = None if stated is None else stated[1:]
        if kept_shape != self.frame_shape:  # the sums would be over another camera's pixels
            raise RecordingError(f"{self.directory}: holds frames of {_size(kept_shape)}, this camera's are "
                                 f"{_size(self.frame_shape)}: continue it with the camera it was recorded with, or "
                                 "start again with --fresh")
        table = read_spots(self.directory / SPOTS, self.frame_shape)
        self._use(table, keep_rows=keep - self.rest_frames)

    def _use(self, table: FiberTable, keep_rows: int = 0) -> None:
        """Sum every later frame over ``table``'s pixel groups (as the per-frame loop does, exactly)."""
        self._sampler = FiberSampler(table)
        self._sums = NpyRows(self.directory / SUMS, (table.n_fibers,), self._sampler.sum_dtype, None,
                             keep_rows=keep_rows)
        if self.pixel_format == "rgb":
            if keep_rows and not (self.directory / COLOURS).exists():
                raise RecordingError(f"{self.directory}: holds no fiber colours to continue after frame "
                                     f"{keep_rows + self.rest_frames} (recorded before colours were kept)")
            self._colours = NpyRows(self.directory / COLOURS, (table.n_fibers, 3), self._sampler.sum_dtype, None,
                                    keep_rows=keep_rows)
        self._found = table

    # -- finding the fibers off the frame thread -------------------------------------

    def _start_finder(self) -> None:
        rest = np.stack(self._rest_copies)

        def find() -> None:
            try:
                self._found = self._find_fibers(rest, self.pixel_format)
            except BaseException as exc:  # noqa: BLE001 - raised on the writer's thread
                self._found = exc

        self._finder = threading.Thread(target=find, name="optitac-find-fibers", daemon=True)
        self._finder.start()

    def _ready(self, wait: bool) -> bool:
        """True once the fiber map is there and in use (waiting for it with ``wait``)."""
        if self._sampler is not None:
            return True
        if self._finder is None:  # (started by the last rest frame's write)
            return False
        if self._finder.is_alive() and not wait:
            return False
        self._finder.join()
        found = self._found
        if isinstance(found, BaseException):
            raise OutputError(f"{self.directory}: cannot find the fibers in the rest frames to keep each fiber's "
                              f"light ({found}); record the frames as they are with --storage raw") from None
        assert isinstance(found, FiberTable)
        packed = io.BytesIO()
        spots: dict[str, Any] = {k: np.asarray(getattr(found, k), dtype) for k, dtype in _SPOT_ARRAYS.items()}
        np.savez(packed, **spots)
        with AtomicFile(self.directory / SPOTS, "wb") as f:
            f.write(packed.getvalue())
        self._use(found)
        self._rest_copies = []
        pending, self._pending = self._pending, []
        for index, frame in pending:
            self._sum(index, frame)
        return True

    # -- FrameStore ---------------------------------------------------------------------

    def _sum(self, index: int, frame: np.ndarray) -> None:
        assert self._sampler is not None and self._sums is not None
        self._sampler.gather(frame)
        self._sums.write(index - self.rest_frames, self._sampler.sums())
        if self._colours is not None:  # the same gathered pixels, channel by channel
            self._colours.write(index - self.rest_frames, self._sampler.channel_sums())

    def write(self, index: int, frame: np.ndarray) -> None:
        if index != self._written:
            raise ValueError(f"frames are kept as fiber sums in order: frame {index} after {self._written}")
        if frame.shape != self.frame_shape:
            raise ValueError(f"frame of shape {frame.shape}, the recording holds {self.frame_shape}")
        self._written += 1
        if index < self.rest_frames:
            assert self._rest is not None
            self._rest.write(index, frame)
            self._rest_copies.append(np.array(frame, dtype=np.uint8))
            if index == self.rest_frames - 1:
                self._start_finder()  # the frames go on while the fibers are found
            return
        if self._ready(wait=False):
            self._sum(index, frame)
            return
        self._pending.append((index, np.array(frame, dtype=np.uint8)))
        if len(self._pending) * frame.nbytes > PENDING_BYTES:
            log.warning("waiting for the fiber map of %s (%d frames in memory)", self.directory, len(self._pending))
            self._ready(wait=True)

    def sync(self) -> None:
        self._ready(wait=True)
        for rows in (self._rest, self._sums, self._colours):
            if rows is not None:
                rows.sync()

    def finish(self, n_frames: int) -> dict[str, Any]:
        if n_frames < self.rest_frames:
            raise RecordingError(f"{self.directory}: {n_frames} frames, fewer than its {self.rest_frames} rest "
                                 "frames")
        self._ready(wait=True)
        assert self._sums is not None and self._found is not None and isinstance(self._found, FiberTable)
        if self._rest is not None:
            self._rest.finish(self.rest_frames)
        self._sums.finish(n_frames - self.rest_frames)
        if self._colours is not None:
            self._colours.finish(n_frames - self.rest_frames)
        return {"storage": "fibers", "frame_shape": list(self.frame_shape), "fibers": self._found.n_fibers}

    def close(self) -> None:
        if self._finder is not None and self._finder.is_alive():
            self._finder.join()
        for rows in (self._rest, self._sums, self._colours):
            if rows is not None:
                rows.close()
