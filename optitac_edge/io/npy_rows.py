"""A ``.npy`` file written a row at a time with ``pwrite``: fixed-size, or open-ended and grown as it fills.

The space is allocated on disk ahead of the rows (``posix_fallocate``: a full
disk fails there, with one line, not with a SIGBUS or a short write later). An
open-ended file's header claims an absurd row count until :meth:`NpyRows.finish`
writes the real one and cuts the file to it; a reader refuses it until then,
which is what an incomplete recording should get.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path

import numpy as np

from optitac_edge.errors import OutputError, RecordingError

#: An open-ended file grows by this many rows at a time.
GROW_ROWS = 256
#: Digits reserved in an open-ended header for the row count.
_COUNT_DIGITS = 15


def npy_header(shape: tuple[int, ...], dtype: np.dtype, length: int | None = None) -> bytes:
    """A ``.npy`` v1.0 header of ``dtype`` and ``shape``, padded to ``length`` bytes (else to a multiple of 64)."""
    text = f"{{'descr': {np.lib.format.dtype_to_descr(np.dtype(dtype))!r}, 'fortran_order': False, " \
           f"'shape': {shape!r}, }}"
    total = length if length is not None else -(-(10 + len(text) + 1) // 64) * 64
    pad = total - 10 - len(text) - 1
    if pad < 0:
        raise ValueError("header does not fit")
    body = (text + " " * pad + "\n").encode("latin1")
    return b"\x93NUMPY\x01\x00" + len(body).to_bytes(2, "little") + body


def npy_shape(path: Path) -> tuple[int, ...] | None:
    """The array shape an ``.npy`` file's header states (nothing of its data read); None when the header cannot
    be read (the file's own reader then says why)."""
    try:
        with path.open("rb") as f:
            major, _minor = np.lib.format.read_magic(f)
            read = np.lib.format.read_array_header_1_0 if major == 1 else np.lib.format.read_array_header_2_0
            shape, _, _ = read(f)
    except (OSError, ValueError):
        return None
    return tuple(int(v) for v in shape)


class NpyRows:
    """Rows of one shape and dtype into a ``.npy`` file at ``path``.

    Parameters
    ----------
    path : Path
    row_shape : tuple of int
    dtype : dtype
    n_rows : int or None
        Rows the file holds; None: open-ended (grown :data:`GROW_ROWS` at a time).
    keep_rows : int
        Open-ended only: continue the file at ``path`` (written by this class, not finished) after its
        first ``keep_rows`` rows.

    Raises
    ------
    OutputError
        The file cannot be written (naming it).
    RecordingError
        ``keep_rows`` asks for rows the file does not hold, or it holds others.
    """

    def __init__(self, path: Path, row_shape: tuple[int, ...], dtype: np.dtype | type, n_rows: int | None,
                 keep_rows: int = 0) -> None:
        self.path = path
        self.row_shape = tuple(int(v) for v in row_shape)
        self.dtype = np.dtype(dtype)
        self.open_ended = n_rows is None
        self.capacity = 0
        self._row_bytes = int(np.prod(self.row_shape, dtype=np.int64)) * self.dtype.itemsize
        self._fd = -1
        try:
            if keep_rows:
                self._continue(keep_rows)
            else:
                shape = (10**_COUNT_DIGITS - 1 if n_rows is None else n_rows, *self.row_shape)
                with path.open("wb") as f:
                    f.write(npy_header(shape, self.dtype))
                    self._offset = f.tell()
                self._fd = os.open(path, os.O_WRONLY)
                self._grow_to(GROW_ROWS if n_rows is None else n_rows)
        except OSError as exc:
            self.close()
            raise OutputError(f"{path}: {exc.strerror or exc}") from None

    def _continue(self, keep: int) -> None:
        try:
            with self.path.open("rb") as f:
                if np.lib.format.read_magic(f) != (1, 0):
                    raise ValueError("not written by this writer")
                shape, _, dtype = np.lib.format.read_array_header_1_0(f)
                offset = f.tell()
            size = self.path.stat().st_size
        except (OSError, ValueError) as exc:
            raise RecordingError(f"{self.path}: cannot continue this recording ({exc})") from None
        if dtype != self.dtype or tuple(shape[1:]) != self.row_shape or size < offset + keep * self._row_bytes:
            raise RecordingError(f"{self.path}: cannot continue this recording (it holds other rows, "
                                 f"or fewer than {keep})")
        self._offset = offset
        self.capacity = (size - offset) // self._row_bytes
        self._fd = os.open(self.path, os.O_WRONLY)
        self._grow_to(keep + GROW_ROWS)

    def _grow_to(self, n_rows: int) -> None:
        """Allocate room for ``n_rows`` rows on disk now."""
        if n_rows <= self.capacity:
            return
        size = self._offset + n_rows * self._row_bytes
        try:
            os.posix_fallocate(self._fd, 0, size)
        except OSError as exc:
            if exc.errno not in (errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL):
                raise
            os.ftruncate(self._fd, size)
        self.capacity = n_rows

    def write(self, index: int, row: np.ndarray) -> None:
        """Row ``index`` (open-ended: any; else below ``n_rows``), of the row shape, cast to the dtype."""
        if index < 0 or (index >= self.capacity and not self.open_ended):
            raise IndexError(f"row {index} outside 0..{self.capacity - 1}")
        data = np.ascontiguousarray(row, dtype=self.dtype)
        if data.shape != self.row_shape:
            raise ValueError(f"row of shape {data.shape}, the file holds {self.row_shape}")
        try:
            if index >= self.capacity:
                self._grow_to(max(index + 1, self.capacity + GROW_ROWS))
            n = os.pwrite(self._fd, data.data.cast("B"), self._offset + index * self._row_bytes)
            if n != self._row_bytes:
                raise OSError(errno.ENOSPC, f"short write ({n} of {self._row_bytes} bytes)")
        except OSError as exc:
            raise OutputError(f"{self.path}: {exc.strerror or exc}") from None

    def sync(self) -> None:
        """Every row written so far onto the disk."""
        try:
            os.fsync(self._fd)
        except OSError as exc:
            raise OutputError(f"{self.path}: {exc.strerror or exc}") from None

    def finish(self, n_rows: int) -> None:
        """The file holds exactly ``n_rows`` rows (open-ended: its header says so), synced, and closed."""
        try:
            if self.open_ended:
                os.ftruncate(self._fd, self._offset + n_rows * self._row_bytes)
                header = npy_header((n_rows, *self.row_shape), self.dtype, self._offset)
                if os.pwrite(self._fd, header, 0) != len(header):
                    raise OSError(errno.EIO, "short write of the header")
            os.fsync(self._fd)
        except OSError as exc:
            self.close()
            raise OutputError(f"{self.path}: {exc.strerror or exc}") from None
        self.close()

    def close(self) -> None:
        """Release the file (idempotent)."""
        if self._fd >= 0:
            fd, self._fd = self._fd, -1
            os.close(fd)
