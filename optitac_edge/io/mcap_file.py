"""An MCAP file written as ``NAME.part`` and renamed to ``NAME`` once complete (both MCAP writers use it)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import IO, Any

from optitac_edge.errors import OutputError


def open_part(final: Path) -> tuple[IO[bytes], Path]:
    """(the open ``final.part`` stream, its path) for an MCAP file that will be ``final``.

    Raises
    ------
    OutputError
        When ``final`` is something other than a regular file, or ``.part`` cannot be written.
    """
    part = final.with_name(final.name + ".part")
    if final.exists() and not final.is_file():
        raise OutputError(f"{final}: exists and is not a regular file")
    try:
        return open(part, "wb"), part
    except OSError as exc:
        raise OutputError(f"cannot write {part}: {exc.strerror or exc}") from None


def complete(writer: Any, stream: IO[bytes], part: Path, final: Path) -> None:
    """Finish the MCAP ``writer`` (its summary and footer), sync ``part`` and rename it to ``final``.

    Raises
    ------
    OutputError
        Naming ``final``; what was written stays in ``part``.
    """
    try:
        writer.finish()
        stream.flush()
        os.fsync(stream.fileno())
        stream.close()
        os.replace(part, final)
    except OSError as exc:
        stream.close()
        raise OutputError(f"cannot complete {final}: {exc.strerror or exc} (the data is in {part})") from None
