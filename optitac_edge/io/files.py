"""Writing output files safely: only regular files, all or nothing, errors as one line naming the file.

Every file optitac-edge writes (bundles, contacts CSV, recordings' metadata,
reports, bench results, exported models) goes through :class:`AtomicFile`:

* a target that exists and is not a regular file (a symbolic link, a device
  such as ``/dev/full``, a directory, a FIFO) is refused, never replaced;
* the data go to a private temporary file in the same directory (``.NAME.PID.tmp``),
  are flushed and fsynced, and only a complete file is renamed over the
  target (then the directory is fsynced): a reader sees the old file or the
  new one, never half of one;
* a failure to write (ENOSPC, EIO, a read-only directory, ...) raises
  :class:`~optitac_edge.errors.OutputError` naming the target, and removes the
  temporary file.
"""

from __future__ import annotations

import contextlib
import os
import stat
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import IO, TYPE_CHECKING, Any

from optitac_edge.errors import OutputError

if TYPE_CHECKING:
    from typing_extensions import Self


def check_output_path(path: str | Path, *, directory: bool = False) -> Path:
    """``path`` as a Path, refused unless it is absent or a regular file (a directory with ``directory``).

    Raises
    ------
    OutputError
        If it exists and is a symbolic link, a device, a FIFO or a socket, or
        of the wrong kind (file vs directory).
    """
    path = Path(path)
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return path
    except OSError as exc:
        raise OutputError(f"{path}: {exc.strerror or exc}") from None
    if stat.S_ISLNK(st.st_mode):
        raise OutputError(f"{path}: is a symbolic link; refusing to replace it (give the real path)")
    if directory:
        if not stat.S_ISDIR(st.st_mode):
            raise OutputError(f"{path}: exists and is not a directory")
    elif stat.S_ISDIR(st.st_mode):
        raise OutputError(f"{path}: is a directory")
    elif not stat.S_ISREG(st.st_mode):
        raise OutputError(f"{path}: exists and is not a regular file (a device, FIFO or socket); refusing to write")
    return path


def _remove_stale_temporaries(path: Path) -> None:
    """Delete temporary files of writes that were killed (their process no longer exists)."""
    for tmp in path.parent.glob(f".{path.name}.*.tmp"):
        try:
            pid = int(tmp.name[len(path.name) + 2:-4])
        except ValueError:
            continue
        if pid == os.getpid():
            continue
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            tmp.unlink(missing_ok=True)
        except OSError:  # alive but not ours: leave it
            continue


def fsync_directory(path: Path) -> None:
    """Make a rename in ``path`` durable (ignored where directories cannot be opened)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


class AtomicFile:
    """A file that appears at ``path`` complete, on :meth:`commit`, or not at all.

    >>> with AtomicFile(path, "w") as f:      # doctest: +SKIP
    ...     f.write("...")                    # committed when the block ends without an exception

    Parameters
    ----------
    path : path-like
        The target (absent or a regular file).
    mode : {"w", "wb"}
        Text or binary.
    newline : str, optional
        As for :func:`open` (text mode).

    Raises
    ------
    OutputError
        On a refused target or any failure to write it.
    """

    def __init__(self, path: str | Path, mode: str = "w", newline: str | None = None) -> None:
        if mode not in ("w", "wb"):
            raise ValueError(f"mode must be 'w' or 'wb', got {mode!r}")
        self.path = check_output_path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            _remove_stale_temporaries(self.path)
            self._tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
            self.file: IO[Any] | None = self._tmp.open(mode, newline=newline) if mode == "w" else self._tmp.open(mode)
        except OSError as exc:
            raise OutputError(f"{self.path}: cannot write ({exc.strerror or exc})") from None

    def write(self, data: Any) -> int:
        """Write ``data`` (str or bytes, as the mode) to the temporary file."""
        assert self.file is not None, "the file was committed or aborted"
        try:
            return int(self.file.write(data))
        except OSError as exc:
            self.abort()
            raise OutputError(f"{self.path}: {exc.strerror or exc}") from None

    def commit(self) -> None:
        """Flush, fsync and rename the complete file onto ``path`` (idempotent)."""
        if self.file is None:
            return
        f, self.file = self.file, None
        try:
            f.flush()
            os.fsync(f.fileno())
            f.close()
            check_output_path(self.path)  # nothing else appeared at the target meanwhile
            os.replace(self._tmp, self.path)
        except OSError as exc:
            try:
                f.close()
            except OSError:
                pass
            self._tmp.unlink(missing_ok=True)
            raise OutputError(f"{self.path}: {exc.strerror or exc}") from None
        except OutputError:
            self._tmp.unlink(missing_ok=True)
            raise
        fsync_directory(self.path.parent)

    def abort(self) -> None:
        """Drop what was written (idempotent); ``path`` is left as it was."""
        if self.file is None:
            return
        f, self.file = self.file, None
        try:
            f.close()
        except OSError:
            pass
        self._tmp.unlink(missing_ok=True)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.abort()


def write_file_atomic(path: str | Path, data: str | bytes) -> None:
    """Write ``data`` to ``path`` as one :class:`AtomicFile` (text for str, binary for bytes)."""
    with AtomicFile(path, "wb" if isinstance(data, bytes) else "w") as f:
        f.write(data)


@contextlib.contextmanager
def sole_writer(target: Path) -> Iterator[None]:
    """While the block runs, this process is the only one of this program writing ``target``: an advisory lock
    (``flock``) on ``.NAME.lock`` beside it, released when the block ends or the process dies. Another writer
    meanwhile is refused in one line (:class:`OutputError`). The lock file is left in place (removing it could
    race a writer that just opened it); it holds nothing."""
    import fcntl

    lock = target.with_name(f".{target.name}.lock")
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise OutputError(f"{target}: cannot take its lock {lock.name} ({exc.strerror or exc})") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise OutputError(f"{target}: another optitac-edge is writing it now (its lock {lock.name} is held); "
                              "one writer per destination") from None
        yield
    finally:
        os.close(fd)
