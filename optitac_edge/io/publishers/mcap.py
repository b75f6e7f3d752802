"""Write the messages to MCAP files (ROS 2 profile, CDR with ros2msg schemas), rotated by size or time.

Needs the ``mcap`` extra (the ``mcap`` package), imported when this backend is
opened. Files open in Foxglove, Lichtblick and the ``mcap`` libraries
(``mcap-ros2-support`` decodes them); see docs/network.md.

A file is written as ``NAME.part`` and renamed to ``NAME`` when it is complete
(rotation or close); after a crash the ``.part`` file holds every chunk written so
far (``mcap recover`` restores its index).

A run never replaces or truncates an earlier one's files (the service starts again
after a power cut with the same ``[mcap] path``): when ``NAME.mcap`` or any
``NAME-NNNN.mcap[.part]`` exists, the run writes ``NAME-NNNN.mcap`` numbered after
the highest of them, and says so. With ``keep_bytes``, once a file is complete the
oldest complete files of the recording are deleted until the rest fit (``.part``
files, which a crash left, are never deleted).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

from mcap.writer import CompressionType, Writer

from optitac_edge.errors import OutputError
from optitac_edge.io.mcap_file import complete, open_part
from optitac_edge.io.publishers.base import Publisher
from optitac_edge.io.ros2.messages import ros2msg_schema

log = logging.getLogger(__name__)

#: The version written in each file's header.
LIBRARY = "optitac-edge"


def rotated_name(path: Path, index: int) -> Path:
    """The ``index``-th file of a rotated recording: ``run.mcap`` -> ``run-0003.mcap``."""
    return path.with_name(f"{path.stem}-{index:04d}{path.suffix or '.mcap'}")


def recording_files(path: Path) -> dict[int, Path]:
    """The files of the recording ``path`` on disk, complete or not (``.part``), by index: ``NAME.mcap``
    is index -1, ``NAME-NNNN.mcap`` index NNNN."""
    suffix = path.suffix or ".mcap"
    pattern = re.compile(rf"{re.escape(path.stem)}(?:-(\d{{4,}}))?{re.escape(suffix)}(\.part)?")
    found: dict[int, Path] = {}
    if path.parent.is_dir():
        for f in path.parent.iterdir():
            m = pattern.fullmatch(f.name)
            if m and f.is_file():
                index = int(m.group(1)) if m.group(1) else -1
                if m.group(2) is None or index not in found:
                    found[index] = f
    return found


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
    """

    def __init__(self, path: str | Path, max_bytes: int = 0, max_ns: int = 0, namespace: str = "",
                 keep_bytes: int = 0, **_network: object) -> None:
        super().__init__()
        self.path = Path(path)
        self.namespace = namespace
        self.max_bytes, self.max_ns, self.keep_bytes = max_bytes, max_ns, keep_bytes
        self._topics: list[tuple[str, str]] = []
        self._seq: list[int] = []
        #: The files completed so far, and those deleted to keep within ``keep_bytes``.
        self.files: list[Path] = []
        self.deleted: list[Path] = []
        earlier = recording_files(self.path)
        for f in sorted(f for f in earlier.values() if f.name.endswith(".part")):
            log.warning("MCAP: %s was left by a run that did not end (a power cut?): kept; 'mcap recover' "
                        "restores its index", f)
        # a rotated recording, or one whose NAME.mcap exists: numbered after every file of it on disk
        self.rotating = bool(max_bytes or max_ns or earlier)
        self._index = max(earlier, default=-1) + 1
        if earlier and not (max_bytes or max_ns):
            log.info("MCAP: %s exists: this run writes %s", self.path, rotated_name(self.path, self._index))
        self._open()

    def _open(self) -> None:
        final = rotated_name(self.path, self._index) if self.rotating else self.path
        self._stream, self._part = open_part(final)
        self._final = final
        self._writer = Writer(self._stream, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library=LIBRARY)
        self._channels: list[int] = []
        self._schemas: dict[str, int] = {}
        for topic, type_name in self._topics:
            self._channels.append(self._channel(topic, type_name))
        self._first_ns: int | None = None
        self._bytes = 0

    def _channel(self, topic: str, type_name: str) -> int:
        schema = self._schemas.get(type_name)
        if schema is None:
            schema = self._writer.register_schema(type_name, "ros2msg", ros2msg_schema(type_name).encode())
            self._schemas[type_name] = schema
        return int(self._writer.register_channel(topic, "cdr", schema))

    def advertise(self, topic: str, type_name: str) -> int:
        self._topics.append((topic, type_name))
        self._channels.append(self._channel(topic, type_name))
        self._seq.append(0)
        return len(self._topics) - 1

    def publish(self, handle: int, payload: bytes, source_ns: int) -> None:
        if self._first_ns is None:
            self._first_ns = source_ns
        elif (self.max_ns and source_ns - self._first_ns >= self.max_ns) or \
                (self.max_bytes and self._bytes >= self.max_bytes):
            self._finish()
            self._index += 1
            self._open()
            self._first_ns = source_ns
        self._seq[handle] += 1
        self._bytes += len(payload)
        try:
            self._writer.add_message(self._channels[handle], source_ns, payload, source_ns, self._seq[handle])
        except OSError as exc:
            raise OutputError(f"cannot write {self._part}: {exc.strerror or exc}") from None

    def _finish(self) -> None:
        complete(self._writer, self._stream, self._part, self._final)
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

    @property
    def where(self) -> str:
        return f"MCAP {self.path}" + (" (rotated)" if self.rotating else "")

    def _close_internal(self) -> None:
        self._finish()

