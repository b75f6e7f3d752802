"""An MCAP file written as ``NAME.part`` and renamed to ``NAME`` once complete (both MCAP writers use it)."""

from __future__ import annotations

import os
from dataclasses import dataclass
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


#: An MCAP writer's open chunk is written and synced after this long of message time, ns.
SYNC_NS = 1_000_000_000


class PeriodicSync:
    """Closes, writes and syncs an MCAP writer's open chunk once ``period_ns`` of message time has passed
    since the last sync (the first message starts the count): a power cut or a kill loses at most about that
    much (the default chunking kept a ``.part`` at 0 bytes for the first 120 s of a run)."""

    def __init__(self, period_ns: int = SYNC_NS) -> None:
        self.period_ns = period_ns
        self._last_ns: int | None = None

    def restart(self) -> None:
        """A new file: its first message starts the count."""
        self._last_ns = None

    def after(self, writer: Any, stream: IO[bytes], t_ns: int) -> None:
        """After a message of time ``t_ns``: sync when due (OSError passes through)."""
        if self._last_ns is None:
            self._last_ns = t_ns
        elif t_ns - self._last_ns >= self.period_ns:
            self._last_ns = t_ns
            writer.flush()
            os.fsync(stream.fileno())


@dataclass(frozen=True)
class PartContents:
    """The messages a ``.part`` file (a run that did not end) holds readable, up to its first damage."""

    messages: int
    first_ns: int | None
    last_ns: int | None


def part_contents(path: Path) -> PartContents:
    """Read ``path`` record by record as far as it goes (chunk CRCs checked), counting its messages.

    A kill or a power cut leaves the last chunk cut short and no summary: everything before is readable.
    Never raises for a damaged or truncated file (an unreadable one holds 0 messages).
    """
    from mcap.records import Message
    from mcap.stream_reader import StreamReader

    count, first, last = 0, None, None
    try:
        with open(path, "rb") as f:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, Message):
                    count += 1
                    first = record.log_time if first is None else first
                    last = record.log_time
    except Exception:  # noqa: BLE001, S110 - the mcap library raises many kinds where a file is cut short
        pass
    return PartContents(count, first, last)
