"""The sending side of the serial link: the queues, ``seq``, the frame loop's own writes and the writer thread.

The frame loop hands a payload to :meth:`FrameWriter.enqueue`, which never blocks and never raises.
When the line is idle (nothing queued, no write under way) and the port has a non-blocking file
descriptor (a UART, USB CDC or pty), the frame loop writes the frame itself with one non-blocking
``write``: no hand-off, no thread wake-up per frame. When that write would block, the frame goes to
the queue; when the kernel took only part of it, the writer thread writes the rest before anything
else. Otherwise the payload goes to a bounded queue; when it is full the oldest frame is dropped and
counted. The writer thread (:meth:`FrameWriter.run`) numbers (``seq``), frames and writes queued
messages, ACKs first. One lock keeps a frame's bytes together whichever thread writes them, and
``seq`` is taken under it, so the wire carries the frames in ``seq`` order.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections import deque
from typing import Any

from optitac_edge.io.protocol import wire
from optitac_edge.io.protocol.messages import ResultCode
from optitac_edge.io.protocol.wire import MsgType
from optitac_edge.io.transports.base import TransportCounters

try:  # pyserial is needed only when this transport is used (lazy registry)
    import serial
except ImportError:  # pragma: no cover - reported when a SerialTransport is created
    serial = None

log = logging.getLogger(__name__)

#: :meth:`FrameWriter._next`'s type of a queued item that is the rest of a frame written in part.
_TAIL = -1


def _nonblocking_fd(port: Any) -> int | None:
    """The port's file descriptor when it is non-blocking (pyserial opens POSIX ports so), else None.

    ``loop://`` and ports without a descriptor, or with a blocking one, are written by the writer
    thread only.
    """
    try:
        fd = port.fileno()
        return fd if isinstance(fd, int) and fd >= 0 and not os.get_blocking(fd) else None
    except Exception:  # noqa: BLE001 - no descriptor (loop://, a test's fake, a closed port)
        return None


class _Numbering:
    """The line's ``seq`` and resync (used holding the write lock): frames in ``seq`` order, each whole."""

    def __init__(self) -> None:
        self.seq = 0
        #: the next frame starts after a delimiter (after (re)connecting or a partial write: it ends
        #: any partial frame on the line)
        self.resync = True

    def frame(self, msg_type: int, t_us: int, payload: bytes) -> bytes:
        """The wire frame with the next ``seq``, after a delimiter when the line must resync."""
        data = wire.encode_frame(msg_type, self.seq, t_us, payload)
        return wire.DELIMITER + data if self.resync else data

    def took(self) -> None:
        """The frame of :meth:`frame` went to the port: the next one takes the next ``seq``."""
        self.seq = (self.seq + 1) & wire.U16
        self.resync = False


#: ACKs waiting for the line: a burst of commands (the protocol allows any) is answered one ACK each.
ACK_QUEUE = 256


class FrameWriter:
    """What goes out on one serial port, in ``seq`` order, from the frame loop and the writer thread.

    Parameters
    ----------
    counters : TransportCounters
        The link's counters (``sent``, ``send_errors``), shared with the transport.
    queue_size : int
        Frames kept while the writer is busy or the port is gone (oldest dropped when full);
        ACKs have their own queue of the same size.
    stop : threading.Event
        Set when the link closes: nothing more is queued, and :meth:`run` drains what is
        queued for at most 0.2 s and returns.
    """

    def __init__(self, counters: TransportCounters, queue_size: int, stop: threading.Event) -> None:
        self.counters = counters
        #: frames dropped from the full send queue (also in counters.send_errors)
        self.dropped = 0
        #: frames dropped because no port was open when they were due (also in send_errors)
        self.dropped_disconnected = 0
        #: frames lost because the line took nothing for the write timeout (the MCU not reading; a part of
        #: the frame may be on the line, which the MCU's CRC refuses; also in send_errors)
        self.timed_out = 0
        #: ACKs written, by result code
        self.acks: dict[ResultCode, int] = {code: 0 for code in ResultCode}
        #: frames the frame loop wrote itself (the line was idle), of ``counters.sent``
        self.direct_writes = 0
        #: of those, frames the kernel took only in part (the writer thread wrote the rest)
        self.partial_writes = 0
        #: the open port (None while there is none); set by :meth:`attach` and :meth:`detach`
        self.port: Any = None
        #: set when a read or write failed: the port is reopened
        self.broken = threading.Event()
        #: a frame is being written by the writer thread
        self.writing = False
        self._stop = stop
        self._lock = threading.Condition()
        self._queue: deque[tuple[int, int, bytes]] = deque()  # (type, t_us, payload)
        self._acks: deque[tuple[int, int]] = deque()  # (seq acked, result)
        self._queue_size = int(queue_size)
        #: Held for every write to the port (one frame's bytes stay together); ``seq`` is taken under it.
        self._write_lock = threading.Lock()
        #: The port's non-blocking file descriptor, for the frame loop's own writes (None: queue only).
        self._direct_fd: int | None = None
        self._os_write = os.write  # the frame loop's write (a test makes the kernel take part of a frame)
        #: The unwritten end of a frame the frame loop wrote in part; the writer sends it first.
        self._tail = b""
        self._numbering = _Numbering()

    @property
    def connected(self) -> bool:
        return self.port is not None and not self.broken.is_set()

    @property
    def pending(self) -> int:
        """Frames waiting in the send queues."""
        with self._lock:
            return len(self._queue) + len(self._acks) + int(bool(self._tail))

    # -- the port ---------------------------------------------------------------------------

    def attach(self, port: Any) -> None:
        """Write to ``port`` from now on: the next frame resyncs the line (after a delimiter)."""
        with self._write_lock:
            self._numbering.resync = True
            self._tail = b""  # the end of a frame begun on the old port: the new one starts afresh
            self._direct_fd = _nonblocking_fd(port)
        self.broken.clear()
        self.port = port
        self.wake()

    def detach(self) -> Any:
        """Stop writing to the port (no write is under way when this returns); the port, to close."""
        with self._write_lock:
            port, self.port = self.port, None
            self._direct_fd = None
        return port

    def wake(self) -> None:
        """Wake the writer thread (a port came, or the link is closing)."""
        with self._lock:
            self._lock.notify_all()

    # -- queueing -------------------------------------------------------------------------

    def enqueue(self, msg_type: int, t_us: int, payload: bytes) -> None:
        """Write the frame now when the line is idle, else queue it; never blocks, never raises."""
        t_us &= wire.U32
        with self._lock:
            if self._stop.is_set():
                return
            # the line is idle: this thread writes the frame itself (taking the write lock here,
            # under the queue's lock, keeps the frames in order with the writer thread's)
            direct = (self._direct_fd is not None and not self._queue and not self._acks and not self._tail
                      and not self.broken.is_set() and self._write_lock.acquire(blocking=False))
            if not direct:
                self._append(msg_type, t_us, payload)
                return
        try:
            written = self._write_direct(msg_type, t_us, payload)
        finally:
            self._write_lock.release()
        with self._lock:
            if not written:  # the kernel's buffer is full: the writer thread waits for room
                self._append(msg_type, t_us, payload)
            elif self._acks or self._tail:  # an ACK came meanwhile, or the rest of this frame
                self._lock.notify()

    def enqueue_ack(self, seq_acked: int, result: int) -> None:
        """Queue the ACK of an incoming frame (written before any queued frame). The ACK queue holds
        :data:`ACK_QUEUE` (a burst of commands is answered whole, one ACK each); only a line that takes nothing
        for that long drops the oldest."""
        with self._lock:
            if len(self._acks) >= max(self._queue_size, ACK_QUEUE):
                self._acks.popleft()
                self.dropped += 1
                self.counters.send_errors += 1
            self._acks.append((seq_acked, int(result)))
            self._lock.notify()

    def _append(self, msg_type: int, t_us: int, payload: bytes) -> None:
        """Queue a frame for the writer thread (holding ``_lock``); the oldest is dropped when full."""
        if len(self._queue) >= self._queue_size:
            self._queue.popleft()
            self.dropped += 1
            self.counters.send_errors += 1
        self._queue.append((msg_type, t_us, payload))
        self._lock.notify()

    def _write_direct(self, msg_type: int, t_us: int, payload: bytes) -> bool:
        """Write one frame from the calling thread without blocking (holding the write lock).

        False when nothing was written (the write would block); True when the frame was
        written, in full or in part (the writer thread sends the rest), or dropped and counted
        (the port failed).
        """
        fd = self._direct_fd
        if fd is None or self.broken.is_set():
            return False
        data = self._numbering.frame(msg_type, t_us, payload)
        try:
            n = self._os_write(fd, data)
        except BlockingIOError:
            return False  # nothing written: the seq is not taken
        except OSError as exc:  # port gone: the I/O thread reopens it
            log.warning("serial write failed: %s", exc)
            self.counters.send_errors += 1
            self.broken.set()
            return True
        self._numbering.took()
        if n < len(data):
            self._tail = data[n:]
            self.partial_writes += 1
        else:
            self.counters.sent += 1
        self.direct_writes += 1
        return True

    # -- writer thread --------------------------------------------------------------------

    def _next(self) -> tuple[int, int, bytes, ResultCode | None] | None:
        """The next frame to write (the rest of a frame written in part, then ACKs), popped; None if none."""
        if self._tail:
            tail, self._tail = self._tail, b""
            return _TAIL, 0, tail, None
        if self._acks:
            seq_acked, result = self._acks.popleft()
            t_us = (time.monotonic_ns() // 1000) & wire.U32
            return MsgType.ACK, t_us, wire.ACK.pack(seq_acked, result), ResultCode(result)
        if self._queue:
            msg_type, t_us, payload = self._queue.popleft()
            return msg_type, t_us, payload, None
        return None

    def _has_work(self) -> bool:
        return bool(self._tail or self._acks or self._queue)

    def run(self) -> None:
        """The writer thread: write what is queued while a port is open, until the link stops."""
        drain_deadline: float | None = None
        while True:
            with self._lock:
                held = False  # the write lock, taken here under the queue's lock
                while not self._stop.is_set():
                    if self._has_work() and self.connected:
                        if self._write_lock.acquire(blocking=False):
                            held = True
                            break
                        # the frame loop holds it for one non-blocking write; it notifies when
                        # work is left for this thread (a millisecond at most otherwise)
                        self._lock.wait(0.001)
                    elif self._has_work():
                        # no port: keep the newest frames; they go out once the port is back
                        self._lock.wait(0.05)
                    else:
                        self._lock.wait(0.5)
                if not held:  # stopping: what is queued goes out for at most 0.2 s
                    if drain_deadline is None:
                        drain_deadline = time.monotonic() + 0.2
                    if not self.connected or time.monotonic() > drain_deadline or not self._has_work():
                        return
                    if not self._write_lock.acquire(timeout=0.05):
                        continue
                item = self._next()
                if item is None:
                    self._write_lock.release()
                    continue
                self.writing = True
            try:
                self._write_frame(item)
            finally:
                self.writing = False
                self._write_lock.release()

    def _write_frame(self, item: tuple[int, int, bytes, ResultCode | None]) -> None:
        """Write one queued frame (holding the write lock; ``seq`` is taken here)."""
        msg_type, t_us, payload, ack_result = item
        port = self.port
        if port is None or self.broken.is_set():
            self.dropped_disconnected += 1
            self.counters.send_errors += 1
            return
        if msg_type == _TAIL:  # the rest of a frame the frame loop wrote in part: no seq of its own
            data = payload
        else:
            data = self._numbering.frame(msg_type, t_us, payload)
            self._numbering.took()
        try:
            n = port.write(data)
            if n is not None and n != len(data):
                raise serial.SerialTimeoutException(f"wrote {n} of {len(data)} bytes")
        except serial.SerialTimeoutException:  # MCU not reading: drop, resync, keep the port
            self.counters.send_errors += 1
            self.timed_out += 1
            self._numbering.resync = True
            return
        except Exception as exc:  # noqa: BLE001 - port gone (OSError, SerialException, ...)
            log.warning("serial write failed: %s", exc)
            self.counters.send_errors += 1
            self.broken.set()
            return
        self.counters.sent += 1
        if ack_result is not None:
            self.acks[ack_result] += 1
