"""Logging that never makes the caller wait: records go through a bounded queue to a writer thread.

A service's stderr is a pipe (journald, a terminal, a parent process); when
nobody reads it, a plain ``StreamHandler`` blocks whoever logs -- the frame
loop included. Here the caller only puts the record in a queue
(:class:`DroppingQueueHandler`); a listener thread writes it. When the queue
is full the record is dropped and counted, and the count is reported once
the writer catches up.
"""

from __future__ import annotations

import logging
import queue
import sys
import threading
from logging.handlers import QueueHandler, QueueListener
from typing import IO, TYPE_CHECKING

if TYPE_CHECKING:
    from typing_extensions import Self

#: Records waiting for the writer before new ones are dropped.
QUEUE_RECORDS = 1000
FORMAT = "%(levelname)s %(name)s: %(message)s"


class DroppingQueueHandler(QueueHandler):
    """A QueueHandler that drops (and counts) a record instead of waiting when the queue is full."""

    def __init__(self, q: queue.Queue[logging.LogRecord]) -> None:
        super().__init__(q)
        self.dropped = 0

    def enqueue(self, record: logging.LogRecord) -> None:
        try:
            self.queue.put_nowait(record)
        except queue.Full:
            self.dropped += 1


class LiveLine:
    """A line redrawn in place on the terminal (``run``'s status line): a log record written to a terminal
    while it shows clears it first, so that the record starts a line of its own (the line is drawn again
    on its next tick). Writers of the line and of records take :attr:`lock`."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.active = False


#: The process's live line (one terminal).
LIVE_LINE = LiveLine()


class _Writer(logging.StreamHandler):  # type: ignore[type-arg,unused-ignore]
    """The listener's handler: writes records, and says how many were dropped before the next one."""

    def __init__(self, stream: IO[str], source: DroppingQueueHandler) -> None:
        super().__init__(stream)
        self._source = source
        self._reported = 0

    def emit(self, record: logging.LogRecord) -> None:
        with LIVE_LINE.lock:
            if LIVE_LINE.active and _is_terminal(self.stream):
                self.stream.write("\r\x1b[2K")
            self._emit(record)

    def _emit(self, record: logging.LogRecord) -> None:
        dropped = self._source.dropped
        if dropped > self._reported:
            lost = logging.makeLogRecord({"name": __name__, "levelno": logging.WARNING, "levelname": "WARNING",
                                          "msg": "%d log records dropped (the log output was not read)",
                                          "args": (dropped - self._reported,)})
            self._reported = dropped
            super().emit(lost)
        super().emit(record)


def _is_terminal(stream: IO[str]) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError, OSError):
        return False


class NonBlockingLogging:
    """Route the root logger (or ``logger``) through a bounded queue to ``stream`` (default stderr)
    until :meth:`stop`. ``always``: install even if the logger has handlers already.

    >>> with NonBlockingLogging(logging.INFO):     # doctest: +SKIP
    ...     logging.getLogger("x").info("never blocks the caller")
    """

    def __init__(self, level: int, stream: IO[str] | None = None, *, logger: str = "", fmt: str = FORMAT,
                 always: bool = False) -> None:
        self._queue: queue.Queue[logging.LogRecord] = queue.Queue(QUEUE_RECORDS)
        self.handler = DroppingQueueHandler(self._queue)
        writer = _Writer(stream if stream is not None else sys.stderr, self.handler)
        writer.setFormatter(logging.Formatter(fmt))
        self._listener = QueueListener(self._queue, writer)
        self._level = level
        self._root = logging.getLogger(logger)
        self._always = always
        if logger:
            self._root.propagate = False
        self._previous: tuple[int, list[logging.Handler]] | None = None

    def start(self) -> Self:
        """Install the queue (like ``logging.basicConfig``: only when the root logger has no handler
        yet, e.g. not under pytest's log capture; the level is set either way)."""
        self._previous = (self._root.level, [])
        self._root.setLevel(self._level)
        if self._root.handlers and not self._always:
            return self
        self._previous = (self._previous[0], [self.handler])
        self._root.addHandler(self.handler)
        self._listener.start()
        return self

    def stop(self) -> None:
        """Write what is queued (blocking now: the work is over) and restore the root logger."""
        if self._previous is None:
            return
        level, installed = self._previous
        self._previous = None
        if installed:
            self._root.removeHandler(self.handler)
            self._listener.stop()
        self._root.setLevel(level)

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
