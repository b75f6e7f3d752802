"""Where a recording is written: the one rule of every writer that a complete recording is never overwritten.

``sim``, ``record`` and ``collect``, into directories and MCAP files: a complete
recording is never overwritten by a run that may not finish. Without
``replace`` it is refused in one line naming ``--fresh``; with it, the new
recording is written beside it (``NAME.new``) and put in its place only once
complete.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from optitac_edge.errors import OutputError
from optitac_edge.io.files import fsync_directory


def holds_recording(path: Path) -> bool:
    """``path`` is a complete recording: a directory with ``meta.json``, or an MCAP file."""
    return (path / "meta.json").is_file() if path.is_dir() else path.suffix == ".mcap" and path.is_file()


def staging_path(target: Path) -> Path:
    """Where a recording that replaces ``target`` is written until it is complete: ``TARGET.new``."""
    return target.with_name(target.name + ".new")


def check_writable_recording(path: str | Path, replace: bool) -> Path:
    """``path`` as a Path, refused when it holds a complete recording and ``replace`` is not given.

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
