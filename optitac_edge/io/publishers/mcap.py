"""Write the messages to MCAP files (ROS 2 profile, CDR with ros2msg schemas), rotated by size or time.

Needs the ``mcap`` extra (the ``mcap`` package), imported when this backend is
opened. Files open in Foxglove, Lichtblick and the ``mcap`` libraries
(``mcap-ros2-support`` decodes them); see docs/network.md.

A file is written as ``NAME.part`` and renamed to ``NAME`` when it is complete
(rotation or close). Every second of messages (their time) the chunk being
written is closed, written and synced, so a power cut or a kill loses at most
about a second: the ``.part`` then holds every chunk before it (``mcap
recover`` restores its index).

What the service wrote is listed in ``NAME.files`` beside the recording (a file
name a line, added before the file is opened and synced): only those files are
ever numbered after or deleted. A run never replaces or truncates an earlier
run's files (the service starts again after a power cut with the same ``[mcap]
path``): when ``NAME.mcap`` or a file of the recording exists, the run writes
``NAME-NNNN.mcap`` numbered after the highest of the recording's files, skipping
any name that is taken, and says so. With ``keep_bytes``, once a file is
complete the oldest complete files of the recording are deleted until the rest
fit (``.part`` files, which a crash left, and files nobody listed -- a user's
``NAME-1999.mcap`` -- are never deleted).

A write that fails (a full disk, an I/O error) does not stop the service: the
file is left as it is (its ``.part`` holds what was written before), the
messages are counted as lost, one warning says so, and a new file is tried
after :data:`RETRY_NS`. :attr:`McapPublisher.summary` says what each file holds.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from optitac_edge.errors import OutputError
from optitac_edge.fields import number, path_text, setting
from optitac_edge.io.device import BoardView
from optitac_edge.io.files import write_file_atomic
from optitac_edge.io.mcap_file import SYNC_NS, PeriodicSync, complete, open_part, part_contents
from optitac_edge.io.publishers.base import Publisher

log = logging.getLogger(__name__)

#: The version written in each file's header.
LIBRARY = "optitac-edge"
#: The chunk being written is closed, written and synced after this long of messages (their time), ns.
FLUSH_NS = SYNC_NS
#: After a failed write, a new file is tried after this long (message time), ns.
RETRY_NS = 60_000_000_000


@dataclass(frozen=True)
class McapPublish:
    """``[publish.mcap]``: a recording of what is published, in MCAP files."""

    path: str = setting(path_text, "", "the MCAP file", required=True)
    max_mb: float = setting(number(0, 1e7), 0.0, "start a new file (NAME-0001.mcap, ...) after this many MB of messages (0: never)")
    max_minutes: float = setting(number(0, 1e6), 0.0, "start a new file after this many minutes (0: never)")
    keep_mb: float = setting(number(0, 1e9), 0.0, "delete the recording's oldest complete files once they hold more than "
                             "this many MB (0: keep all)")


def rotated_name(path: Path, index: int) -> Path:
    """The ``index``-th file of a rotated recording: ``run.mcap`` -> ``run-0003.mcap`` (``-1``: ``run.mcap``)."""
    if index < 0:
        return path
    return path.with_name(f"{path.stem}-{index:04d}{path.suffix or '.mcap'}")


def manifest_path(path: Path) -> Path:
    """``NAME.files``: the files the service wrote for the recording ``path``, a name a line."""
    return path.with_name(path.name + ".files")


def recording_files(path: Path) -> dict[int, Path]:
    """The files of the recording ``path`` the service wrote (listed in :func:`manifest_path`) and still on
    disk, complete or not (``.part``), by index: ``NAME.mcap`` is index -1, ``NAME-NNNN.mcap`` index NNNN."""
    suffix = path.suffix or ".mcap"
    pattern = re.compile(rf"{re.escape(path.stem)}(?:-(\d{{4,}}))?{re.escape(suffix)}")
    found: dict[int, Path] = {}
    try:
        listed = manifest_path(path).read_text(encoding="utf-8").split()
    except (OSError, UnicodeDecodeError):
        return found
    for name in listed:
        m = pattern.fullmatch(name)
        if not m:
            continue
        index = int(m.group(1)) if m.group(1) else -1
        final = path.with_name(name)
        part = final.with_name(final.name + ".part")
        if final.is_file():
            found[index] = final
        elif part.is_file():
            found[index] = part
    return found


def _taken(path: Path) -> bool:
    return path.exists() or path.with_name(path.name + ".part").exists()


@dataclass
class McapFile:
    """One file of the recording: where it is, what it holds, and whether it is complete."""

    path: Path
    messages: int = 0
    first_ns: int | None = None
    last_ns: int | None = None
    complete: bool = False
    failed: str = ""

    def describe(self) -> str:
        span = ""
        if self.first_ns is not None and self.last_ns is not None:
            span = f" over {(self.last_ns - self.first_ns) / 1e9:.1f} s"
        if self.complete:
            return f"{self.path}: {self.messages} messages{span}"
        return (f"{self.path}: {self.messages} messages{span} before {self.failed} (incomplete: 'mcap recover' "
                "restores its index)")


class McapPublisher(Publisher):
    """Every message in MCAP files.

    Parameters
    ----------
    path : path
        The file; with rotation, ``STEM-0000.mcap``, ``STEM-0001.mcap``, ...
    max_bytes : int
        Start a new file after this many bytes of messages, before compression (0: never).
    max_ns : int
        Start a new file after this long of messages, ns (0: never).
    namespace : str
        The ROS 2 namespace of the topics (as the network's).
    keep_bytes : int
        Delete the oldest complete files of the recording once they hold more than this (0: keep all).
    flush_ns : int
        Close, write and sync the chunk being written after this long of messages (their time), ns.
    open_file : callable, optional
        ``open_part(final) -> (stream, part path)`` (default :func:`~optitac_edge.io.mcap_file.open_part`;
        tests give one whose writes fail).

    Raises
    ------
    OutputError
        When the first file cannot be created (a directory that does not exist, no permission).
    """

    Section = McapPublish

    @classmethod
    def from_config(cls, section: McapPublish, board: BoardView) -> McapPublisher:
        """``[publish.mcap]`` (sizes in MB, times in minutes) under the board's namespace."""
        return cls(Path(section.path), max_bytes=int(section.max_mb * 1e6), max_ns=int(section.max_minutes * 60e9),
                   namespace=board.namespace, keep_bytes=int(section.keep_mb * 1e6))

    def __init__(self, path: str | Path, max_bytes: int = 0, max_ns: int = 0, namespace: str = "",
                 keep_bytes: int = 0, flush_ns: int = FLUSH_NS,
                 open_file: Callable[[Path], tuple[IO[bytes], Path]] | None = None, **_network: object) -> None:
        super().__init__()
        self.path = Path(path)
        if self.path.exists() and not self.path.is_file():
            raise OutputError(f"{self.path}: exists and is not a regular file")
        self.namespace = namespace
        self.max_bytes, self.max_ns, self.keep_bytes = max_bytes, max_ns, keep_bytes
        self._sync = PeriodicSync(flush_ns)
        self._open_file = open_file or open_part
        self._topics: list[tuple[str, str]] = []
        self._seq: list[int] = []
        #: Every file this run wrote, in order (the last one is being written unless closed).
        self.written: list[McapFile] = []
        #: The files completed so far, and those deleted to keep within ``keep_bytes``.
        self.files: list[Path] = []
        self.deleted: list[Path] = []
        #: Messages lost to failed writes.
        self.lost = 0
        earlier = recording_files(self.path)
        for f in sorted(f for f in earlier.values() if f.name.endswith(".part")):
            log.warning("MCAP: %s was left by a run that did not end (a power cut?): kept; 'mcap recover' "
                        "restores its index", f)
        # a rotated recording, or one whose NAME.mcap exists: numbered after every file of it on disk
        self.rotating = bool(max_bytes or max_ns or earlier or _taken(self.path))
        self._index = max(earlier, default=-1) + 1 if self.rotating else -1
        if self.rotating and not (max_bytes or max_ns):
            log.info("MCAP: %s exists: this run writes %s", self.path, self._free_name())
        self._writer: Any = None
        self._failed_at: int | None = None
        self._open()

    # -- files ---------------------------------------------------------------------

    def _free_name(self) -> Path:
        """The next name of the recording that no file takes (a user's file of that name is left alone)."""
        while self.rotating and _taken(rotated_name(self.path, self._index)):
            self._index += 1
        return rotated_name(self.path, self._index)

    def _list(self, final: Path) -> None:
        """Add ``final`` to the recording's manifest, durably, before it is opened."""
        with open(manifest_path(self.path), "a", encoding="utf-8") as f:
            f.write(final.name + "\n")
            f.flush()
            os.fsync(f.fileno())

    def _open(self) -> None:
        final = self._free_name()
        try:
            self._list(final)
        except OSError as exc:
            raise OutputError(f"cannot write {manifest_path(self.path)}: {exc.strerror or exc}") from None
        self._stream, self._part = self._open_file(final)
        self._final = final
        self._file = McapFile(self._part)
        self.written.append(self._file)
        from mcap.writer import CompressionType, Writer  # not at import: the board config reads the section

        self._writer = Writer(self._stream, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library=LIBRARY)
        self._channels: list[int] = []
        self._schemas: dict[str, int] = {}
        for topic, type_name in self._topics:
            self._channels.append(self._channel(topic, type_name))
        self._sync.restart()
        self._bytes = 0

    def _channel(self, topic: str, type_name: str) -> int:
        schema = self._schemas.get(type_name)
        if schema is None:
            from optitac_edge.io.ros2.messages import ros2msg_schema  # numpy: not when a board is read

            schema = self._writer.register_schema(type_name, "ros2msg", ros2msg_schema(type_name).encode())
            self._schemas[type_name] = schema
        return int(self._writer.register_channel(topic, "cdr", schema))

    def advertise(self, topic: str, type_name: str) -> int:
        self._topics.append((topic, type_name))
        self._seq.append(0)
        if self._writer is not None:
            try:
                self._channels.append(self._channel(topic, type_name))
            except OSError as exc:
                self._fail(exc, 0)
        return len(self._topics) - 1

    # -- messages --------------------------------------------------------------------

    def publish(self, handle: int, payload: bytes, source_ns: int) -> None:
        self._seq[handle] += 1
        if self._writer is None and not self._retry(source_ns):
            self.lost += 1
            return
        counted = False  # this message in its file's count (a failure after that must not count it twice)
        try:
            first = self._file.first_ns
            if first is not None and ((self.max_ns and source_ns - first >= self.max_ns) or
                                      (self.max_bytes and self._bytes >= self.max_bytes)):
                self._finish()
                self._index += 1
                self._open()
            self._bytes += len(payload)
            self._writer.add_message(self._channels[handle], source_ns, payload, source_ns, self._seq[handle])
            f = self._file
            f.messages += 1
            counted = True
            f.first_ns = source_ns if f.first_ns is None else f.first_ns
            f.last_ns = source_ns
            self._sync.after(self._writer, self._stream, source_ns)
        except (OSError, OutputError) as exc:  # OutputError: a rotation that could not complete or open a file
            self._fail(exc, source_ns, 0 if counted else 1)

    def _fail(self, exc: BaseException, source_ns: int, lost: int = 1) -> None:
        """A write failed: leave the file as it is, count (``lost``: messages not in the file's count), warn once
        per file, try a new file later."""
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        self._file.failed = f"a failed write ({why})"
        self.lost += lost
        log.warning("MCAP: cannot write %s (%s): it keeps what was written before; messages are counted as lost "
                    "and a new file is tried every %d s", self._part, why, RETRY_NS // 10**9)
        try:
            self._stream.close()
        except OSError:
            pass
        f = self._file
        if not f.complete:  # (a rotation whose next file could not open leaves the complete one as it is)
            on_disk = part_contents(self._part)  # what the file holds readable: the messages after it are lost
            self.lost += f.messages - on_disk.messages
            f.messages, f.first_ns, f.last_ns = on_disk.messages, on_disk.first_ns, on_disk.last_ns
        self._writer = None
        self._failed_at = source_ns

    def _retry(self, source_ns: int) -> bool:
        """A new file after a failed one, once :data:`RETRY_NS` has passed (True when one is open)."""
        if self._failed_at is not None and source_ns - self._failed_at < RETRY_NS:
            return False
        self._failed_at = source_ns
        self._index += 1
        try:
            self._open()
        except (OSError, OutputError) as exc:
            log.debug("MCAP: a new file could not be opened yet: %s", exc)
            self._writer = None
            return False
        return True

    def _finish(self) -> None:
        complete(self._writer, self._stream, self._part, self._final)
        self._file.path, self._file.complete = self._final, True
        self.files.append(self._final)
        log.info("MCAP: wrote %s", self._final)
        if self.keep_bytes:
            self._delete_oldest()

    def _delete_oldest(self) -> None:
        """Delete the oldest complete files of the recording (never the one just written) until the rest
        hold at most ``keep_bytes``."""
        files = sorted((i, f) for i, f in recording_files(self.path).items() if not f.name.endswith(".part"))
        sizes = {f: f.stat().st_size for _, f in files}
        total = sum(sizes.values())
        for _, f in files:
            if total <= self.keep_bytes or f == self._final:
                break
            try:
                f.unlink()
            except OSError as exc:
                log.warning("MCAP: cannot delete %s to keep within %d MB: %s", f, self.keep_bytes // 10**6, exc)
                break
            total -= sizes[f]
            self.deleted.append(f)
            log.info("MCAP: deleted %s (the recording keeps its newest %d MB)", f, self.keep_bytes // 10**6)
        self._unlist({f.name for f in self.deleted})

    def _unlist(self, names: set[str]) -> None:
        """Take deleted files' names off the manifest (atomically): a user's file that later takes such a
        name is not the service's to delete."""
        manifest = manifest_path(self.path)
        try:
            listed = manifest.read_text(encoding="utf-8").split()
            kept = [n for n in listed if n not in names]
            if len(kept) != len(listed):
                write_file_atomic(manifest, "".join(n + "\n" for n in kept))
        except (OSError, UnicodeDecodeError, OutputError) as exc:
            log.warning("MCAP: cannot update %s: %s", manifest, exc)

    @property
    def where(self) -> str:
        return f"MCAP {self.path}" + (" (numbered)" if self.rotating else "")

    @property
    def undelivered(self) -> int:
        return self.lost

    @property
    def summary(self) -> list[str]:
        """What each file of this run holds (the messages lost to failed writes: :attr:`undelivered`)."""
        return [f.describe() for f in self.written if f.messages or not f.failed]

    def _close_internal(self) -> None:
        if self._writer is None:
            return
        try:
            self._finish()
        except OutputError as exc:
            self._file.failed = f"the end of the run ({exc})"
            log.warning("MCAP: %s", exc)
