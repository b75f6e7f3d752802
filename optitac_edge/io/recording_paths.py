"""Where a recording is written: the one rule of every writer that a complete recording is never overwritten.

``sim``, ``record`` and ``collect``, into directories and MCAP files: a complete
recording is never overwritten by a run that may not finish. Without
``replace`` it is refused in one line naming ``--fresh``; with it, the new
recording is written beside it (``NAME.new``) and put in its place only once
complete.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from optitac_edge.errors import OutputError
from optitac_edge.io.files import fsync_directory

log = logging.getLogger(__name__)
#: The signals a terminal or systemd stops a command with: held back while a replacement renames.
_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def holds_recording(path: Path) -> bool:
    """``path`` is a complete recording: a directory with ``meta.json``, or an MCAP file."""
    return (path / "meta.json").is_file() if path.is_dir() else path.suffix == ".mcap" and path.is_file()


def staging_path(target: Path) -> Path:
    """Where a recording that replaces ``target`` is written until it is complete: ``TARGET.new``."""
    return target.with_name(target.name + ".new")


def aside_path(target: Path) -> Path:
    """Where a replaced recording waits while the new one takes its name: ``TARGET.old``."""
    return target.with_name(target.name + ".old")


def interrupted_swap(target: Path) -> Path | None:
    """A complete recording a replacement left beside ``target`` when it was killed between its two renames
    (``target`` gone): the new one (``TARGET.new``) or else the replaced one (``TARGET.old``); None when
    ``target`` exists or neither is complete."""
    if target.exists() or target.is_symlink():
        return None
    return next((p for p in (staging_path(target), aside_path(target)) if holds_recording(p)), None)


def recover_swap(target: Path) -> None:
    """Finish a replacement killed between its two renames: the complete recording beside ``target`` (the
    new one first) takes its name. Nothing is deleted.

    Raises
    ------
    OutputError
        The rename fails.
    """
    left = interrupted_swap(target)
    if left is None:
        return
    try:
        os.rename(left, target)
        fsync_directory(target.parent)
    except OSError as exc:
        raise OutputError(f"{target}: missing, and the complete recording {left} cannot take its place: "
                          f"{exc.strerror or exc}; rename it to {target.name}") from None
    log.warning("%s: a replacement was interrupted between its two renames; %s took its place", target, left.name)


def check_writable_recording(path: str | Path, replace: bool) -> Path:
    """``path`` as a Path, refused when it holds a complete recording and ``replace`` is not given. A
    replacement killed between its renames is finished first (:func:`recover_swap`).

    Raises
    ------
    OutputError
        One line naming the recording and ``--fresh``.
    """
    target = Path(path)
    recover_swap(target)
    if holds_recording(target) and not replace:
        raise OutputError(f"{target}: holds a complete recording; give another output, or --fresh to replace it "
                          "(it is kept until the new one is complete)")
    return target


@contextmanager
def _signals_held() -> Iterator[None]:
    """Hold back SIGINT, SIGTERM and SIGHUP: each that comes meanwhile goes to its own handler once the block ends
    (the main thread only: Python's handlers run there, and only there can they be swapped).

    Masking the signals (pthread_sigmask) is not enough: another thread of the process takes the signal and
    Python still runs its handler in the main thread at once.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pending: list[int] = []

    def hold(signum: int, _frame: object) -> None:
        pending.append(signum)

    previous = {s: signal.getsignal(s) for s in _STOP_SIGNALS}
    for s in _STOP_SIGNALS:
        signal.signal(s, hold)
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, signal.SIG_DFL if handler is None else handler)
        for signum in pending:
            signal.raise_signal(signum)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def swap_in(staging: Path, target: Path) -> None:
    """Put the complete recording ``staging`` in the place of the complete recording ``target``.

    ``target`` is renamed aside first, so at every moment one complete recording is at one of the
    two names, then removed. Ctrl-C and the stop signals wait until both renames are done; a kill
    between them is finished by the next writer (:func:`recover_swap`) and named by every reader.
    """
    aside = aside_path(target)
    try:
        _remove(aside)
        with _signals_held():
            os.rename(target, aside)
            os.rename(staging, target)
            fsync_directory(target.parent)
    except OSError as exc:
        raise OutputError(f"cannot put {staging} in the place of {target}: {exc.strerror or exc} "
                          f"(the new recording is complete in {staging})") from None
    _remove(aside)
