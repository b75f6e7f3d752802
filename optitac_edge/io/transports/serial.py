"""Serial link to the gripper MCU: protocol v1 (docs/protocol.md) over a UART, USB CDC or pty.

Threads
-------
* the caller (the frame loop) packs a payload; :meth:`SerialTransport.send_contact` never
  blocks and never raises. When the line is idle (nothing queued, no write under way) and
  the port has a non-blocking file descriptor (a UART, USB CDC or pty), it writes the frame
  itself with one non-blocking ``write``: no hand-off, no thread wake-up per frame. When the
  write would block, the frame goes to the queue; when the kernel took only part of it, the
  writer thread writes the rest before anything else. Otherwise it appends the payload to a
  bounded queue; when the queue is full the oldest frame is dropped and counted;
* a writer thread numbers (``seq``), frames and writes queued messages, ACKs first; one lock
  keeps a frame's bytes together whichever thread writes them, and ``seq`` is taken under it,
  so the wire carries the frames in ``seq`` order;
* an I/O thread owns the port: it opens it, reads and decodes incoming bytes, answers each
  command with an ACK, queues validated commands for :meth:`poll_commands`, and reopens the
  port with exponential backoff when it fails or vanishes (``counters.reconnects``).

The port is opened with ``serial.serial_for_url`` so ``loop://``, ``/dev/ttyUSB0`` and
pty slave paths all work.
"""

from __future__ import annotations

import errno
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

from optitac_edge.errors import TransportError
from optitac_edge.io.backoff import Backoff
from optitac_edge.io.protocol import wire, wire_v2
from optitac_edge.io.protocol.decoder import FrameDecoder
from optitac_edge.io.protocol.messages import (
    Command,
    ContactMessage,
    ContactV2Message,
    ReleaseMessage,
    ResultCode,
    StatusMessage,
)
from optitac_edge.io.protocol.wire import Frame, MsgType
from optitac_edge.io.transports.base import Transport

try:  # pyserial is needed only when this transport is used (lazy registry)
    import serial
except ImportError:  # pragma: no cover - reported when a SerialTransport is created
    serial = None

log = logging.getLogger(__name__)
#: errno of a port that is not there (yet): unplugged adapter, udev not done. Anything else is fatal at start.
_ABSENT = frozenset({errno.ENOENT, errno.ENODEV, errno.ENXIO, errno.EIO})
#: errno of a port another process holds (pyserial's exclusive flock).
_LOCKED = frozenset({errno.EAGAIN, errno.EWOULDBLOCK})


def _errno(exc: BaseException) -> int | None:
    """The errno of an open failure (pyserial wraps the OSError and keeps its errno)."""
    return getattr(exc, "errno", None)


#: :meth:`SerialTransport._next`'s type of a queued item that is the rest of a frame written in part.
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


_IO_ERRORS: tuple[type[BaseException], ...] = (OSError,) if serial is None else (
    OSError, serial.SerialException)


class SerialTransport(Transport):
    """Protocol v1, and v2 when the MCU asks for it, over a serial port.

    Parameters
    ----------
    url : str
        Device path or pyserial URL (``/dev/ttyAMA0``, ``/dev/pts/3``, ``loop://``).
    baudrate : int
        921600 by default (8N1, no flow control).
    queue_size : int
        Outgoing CONTACT/STATUS frames kept while the writer is busy or the port is gone
        (oldest dropped when full); ACKs have their own queue of the same size.
    require_port : bool
        True: raise :class:`TransportError` when the port cannot be opened at start.
        False: when the port is not present (no such device), start disconnected and
        keep retrying in the background. A bad URL, a port locked by another
        process, or any other failure (e.g. permission) is refused either way.
    read_timeout, write_timeout : float
        Port timeouts, seconds (bound how long :meth:`close` can take).
    backoff_min, backoff_max : float
        Reconnect delays, seconds, doubling from min to max after each failed attempt.
    on_frame : callable, optional
        Called from the I/O thread with every valid incoming :class:`Frame` (tests, tools).
    command_queue_size : int
        Validated commands kept for :meth:`poll_commands` (oldest dropped when full).
    open_port : callable, optional
        Opens the port (default: ``serial.serial_for_url`` of ``url`` with the timeouts
        above); a fake port or one a test unplugs goes in here.
    """

    def __init__(self, url: str, baudrate: int = 921600, queue_size: int = 8,  # noqa: PLR0913
                 *, require_port: bool = True, read_timeout: float = 0.05,
                 write_timeout: float = 0.2, backoff_min: float = 0.05, backoff_max: float = 1.0,
                 on_frame: Callable[[Frame], None] | None = None,
                 command_queue_size: int = 32, open_port: Callable[[], Any] | None = None) -> None:
        super().__init__()
        if serial is None:
            raise TransportError("the serial transport needs pyserial (pip install pyserial)")
        if queue_size < 1:
            raise TransportError(f"queue_size must be >= 1, got {queue_size}")
        self.url = url
        self.baudrate = int(baudrate)
        self.read_timeout = float(read_timeout)
        self.write_timeout = float(write_timeout)
        self.backoff_min = float(backoff_min)
        self.backoff_max = float(backoff_max)
        self.on_frame = on_frame
        self._open_port = open_port
        self.decoder = FrameDecoder()
        #: frames dropped from the full send queue (also in counters.send_errors)
        self.dropped = 0
        #: frames dropped because no port was open when they were due (also in send_errors)
        self.dropped_disconnected = 0
        #: ACKs written, by result code
        self.acks: dict[ResultCode, int] = {code: 0 for code in ResultCode}
        #: valid frames of a type the sensor sends (echo, crossed wires), dropped unanswered
        self.unexpected = 0
        #: commands dropped from a full command queue (service loop not polling)
        self.commands_dropped = 0

        self._lock = threading.Condition()
        self._queue: deque[tuple[int, int, bytes]] = deque()  # (type, t_us, payload)
        self._acks: deque[tuple[int, int]] = deque()  # (seq acked, result)
        self._queue_size = int(queue_size)
        self._commands: deque[Command] = deque()
        self._command_queue_size = int(command_queue_size)
        self._seq = 0
        #: Held for every write to the port (one frame's bytes stay together); ``seq`` is taken under it.
        self._write_lock = threading.Lock()
        #: The port's non-blocking file descriptor, for the frame loop's own writes (None: queue only).
        self._direct_fd: int | None = None
        self._os_write = os.write  # the frame loop's write (a test makes the kernel take part of a frame)
        #: The unwritten end of a frame the frame loop wrote in part; the writer sends it first.
        self._tail = b""
        #: frames the frame loop wrote itself (the line was idle), of ``counters.sent``
        self.direct_writes = 0
        #: of those, frames the kernel took only in part (the writer thread wrote the rest)
        self.partial_writes = 0
        self._stop = threading.Event()
        self._broken = threading.Event()
        self._port: Any = None
        self._ever_opened = False
        self._resync = True

        try:
            self._set_port(self._open())
        except (ValueError, KeyError, TypeError) as exc:  # pyserial's answer to a bad URL or URL option
            raise TransportError(f"serial port {url!r}: not a valid device or URL ({exc})") from None
        except _IO_ERRORS as exc:
            if _errno(exc) in _LOCKED:
                raise TransportError(f"serial port {url!r} is in use by another process "
                                     "(another optitac-edge?)") from None
            if require_port or _errno(exc) not in _ABSENT:
                raise TransportError(f"cannot open serial port {url!r}: {exc}") from None
            log.warning("serial port %s not present (%s); streaming as soon as it appears", url,
                        exc.strerror if isinstance(exc, OSError) and exc.strerror else exc)
        self._io_thread = threading.Thread(target=self._io_loop, name="optitac-serial-io", daemon=True)
        self._writer_thread = threading.Thread(target=self._write_loop, name="optitac-serial-tx",
                                               daemon=True)
        self._io_thread.start()
        self._writer_thread.start()

    @classmethod
    def from_link(cls, link: Any, sensor_ids: Sequence[int]) -> SerialTransport:
        """``[link] serial_url``, ``baudrate``. A port that is not there yet (MCU unplugged, udev not done) is
        waited for, not fatal: the service streams as soon as it appears."""
        return cls(link.serial_url, baudrate=link.baudrate, require_port=False)

    # -- Transport API (frame loop side) --------------------------------------------------

    protocols = (1, 2)

    def send_contact(self, message: ContactMessage) -> None:
        """Queue one CONTACT; never blocks, never raises (drops are counted)."""
        self._send(MsgType.CONTACT, message, wire.contact_payload)

    def send_contact_v2(self, message: ContactV2Message) -> None:
        """Queue one CONTACT2 (protocol v2); never blocks, never raises (drops are counted)."""
        self._send(MsgType.CONTACT2, message, wire_v2.contact2_payload)

    def send_release(self, message: ReleaseMessage) -> None:
        """Queue one RELEASE (protocol v2); never blocks, never raises."""
        self._send(MsgType.RELEASE, message, wire_v2.release_payload)

    def send_status(self, message: StatusMessage) -> None:
        """Queue one STATUS; never blocks, never raises."""
        self._send(MsgType.STATUS, message, wire.status_payload)

    def _send(self, msg_type: MsgType, message: Any, payload_of: Callable[[Any], bytes]) -> None:
        """Encode ``message`` (with its own sensor id: one link carries every sensor of a board) and queue
        (or write) it; a message that cannot be encoded is logged and counted, never raised to the frame loop."""
        try:
            self._enqueue(msg_type, int(message.t_us), payload_of(message))
        except Exception:
            log.exception("%s not encodable", msg_type.name)
            self.counters.send_errors += 1

    def poll_commands(self) -> list[Command]:
        """Validated commands received since the last call, oldest first (already ACKed)."""
        with self._lock:
            out = list(self._commands)
            self._commands.clear()
        return out

    @property
    def connected(self) -> bool:
        return self._port is not None and not self._broken.is_set()

    @property
    def pending(self) -> int:
        """Frames waiting in the send queues."""
        with self._lock:
            return len(self._queue) + len(self._acks) + int(bool(self._tail))

    def stats(self) -> dict[str, Any]:
        """Every counter, flat (for STATUS and logs)."""
        c = self.counters
        out: dict[str, Any] = {
            "sent": c.sent, "send_errors": c.send_errors, "received": c.received,
            "rx_errors": c.rx_errors, "reconnects": c.reconnects, "dropped": self.dropped,
            "dropped_disconnected": self.dropped_disconnected, "unexpected": self.unexpected,
            "direct_writes": self.direct_writes, "partial_writes": self.partial_writes,
            "commands_dropped": self.commands_dropped, "connected": self.connected,
        }
        out.update({f"rx_{k}": v for k, v in self.decoder.counters.as_dict().items()})
        out.update({f"ack_{code.name.lower()}": n for code, n in self.acks.items()})
        return out

    def wait_idle(self, timeout: float = 1.0) -> bool:
        """Wait until the send queues are empty (tests, orderly shutdown); False on timeout."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.pending == 0 and not self._writing:
                return True
            time.sleep(0.002)
        return False

    # -- queueing -------------------------------------------------------------------------

    _writing = False

    def _enqueue(self, msg_type: int, t_us: int, payload: bytes) -> None:
        t_us &= wire.U32
        with self._lock:
            if self._closed:
                return
            # the line is idle: this thread writes the frame itself (taking the write lock here,
            # under the queue's lock, keeps the frames in order with the writer thread's)
            direct = (self._direct_fd is not None and not self._queue and not self._acks and not self._tail
                      and not self._broken.is_set() and self._write_lock.acquire(blocking=False))
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

    def _append(self, msg_type: int, t_us: int, payload: bytes) -> None:
        """Queue a frame for the writer thread (holding ``_lock``); the oldest is dropped when full."""
        if len(self._queue) >= self._queue_size:
            self._queue.popleft()
            self.dropped += 1
            self.counters.send_errors += 1
        self._queue.append((msg_type, t_us, payload))
        self._lock.notify()

    def _wire_bytes(self, msg_type: int, t_us: int, payload: bytes) -> bytes:
        """The wire frame with the next ``seq`` (holding the write lock), after a delimiter when the line
        must resync (after (re)connecting or a partial write: it ends any partial frame)."""
        data = wire.encode_frame(msg_type, self._seq, t_us, payload)
        return wire.DELIMITER + data if self._resync else data

    def _took_seq(self) -> None:
        """The frame of :meth:`_wire_bytes` went to the port: the next one takes the next ``seq``."""
        self._seq = (self._seq + 1) & wire.U16
        self._resync = False

    def _write_direct(self, msg_type: int, t_us: int, payload: bytes) -> bool:
        """Write one frame from the calling thread without blocking (holding the write lock).

        False when nothing was written (the write would block); True when the frame was
        written, in full or in part (the writer thread sends the rest), or dropped and counted
        (the port failed).
        """
        fd = self._direct_fd
        if fd is None or self._broken.is_set():
            return False
        data = self._wire_bytes(msg_type, t_us, payload)
        try:
            n = self._os_write(fd, data)
        except BlockingIOError:
            return False  # nothing written: the seq is not taken
        except OSError as exc:  # port gone: the I/O thread reopens it
            log.warning("serial write failed: %s", exc)
            self.counters.send_errors += 1
            self._broken.set()
            return True
        self._took_seq()
        if n < len(data):
            self._tail = data[n:]
            self.partial_writes += 1
        else:
            self.counters.sent += 1
        self.direct_writes += 1
        return True

    def _enqueue_ack(self, seq_acked: int, result: int) -> None:
        with self._lock:
            if len(self._acks) >= self._queue_size:
                self._acks.popleft()
                self.dropped += 1
                self.counters.send_errors += 1
            self._acks.append((seq_acked, int(result)))
            self._lock.notify()

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

    def _write_loop(self) -> None:
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
                self._writing = True
            try:
                self._write_frame(item)
            finally:
                self._writing = False
                self._write_lock.release()

    def _write_frame(self, item: tuple[int, int, bytes, ResultCode | None]) -> None:
        """Write one queued frame (holding the write lock; ``seq`` is taken here)."""
        msg_type, t_us, payload, ack_result = item
        port = self._port
        if port is None or self._broken.is_set():
            self.dropped_disconnected += 1
            self.counters.send_errors += 1
            return
        if msg_type == _TAIL:  # the rest of a frame the frame loop wrote in part: no seq of its own
            data = payload
        else:
            data = self._wire_bytes(msg_type, t_us, payload)
            self._took_seq()
        try:
            n = port.write(data)
            if n is not None and n != len(data):
                raise serial.SerialTimeoutException(f"wrote {n} of {len(data)} bytes")
        except serial.SerialTimeoutException:  # MCU not reading: drop, resync, keep the port
            self.counters.send_errors += 1
            self._resync = True
            return
        except Exception as exc:  # noqa: BLE001 - port gone (OSError, SerialException, ...)
            log.warning("serial write failed: %s", exc)
            self.counters.send_errors += 1
            self._broken.set()
            return
        self.counters.sent += 1
        if ack_result is not None:
            self.acks[ack_result] += 1

    # -- I/O thread: port ownership, reading ---------------------------------------------

    def _open(self) -> Any:
        if self._open_port is not None:
            return self._open_port()
        # exclusive: a second process on the same port is refused (flock), not interleaved
        return serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=self.read_timeout,
                                     write_timeout=self.write_timeout, exclusive=True)

    def _set_port(self, port: Any) -> None:
        if self._ever_opened:
            self.counters.reconnects += 1
        self._ever_opened = True
        self.decoder.reset()
        with self._write_lock:
            self._resync = True
            self._tail = b""  # the end of a frame begun on the old port: the new one starts afresh
            self._direct_fd = _nonblocking_fd(port)
        self._broken.clear()
        self._port = port
        with self._lock:
            self._lock.notify_all()

    def _drop_port(self) -> None:
        with self._write_lock:  # no write is under way on the descriptor being closed
            port, self._port = self._port, None
            self._direct_fd = None
            if port is not None:
                try:
                    port.close()
                except Exception as exc:  # noqa: BLE001 - closing a vanished port may fail
                    log.debug("closing %s: %s", self.url, exc)

    def _io_loop(self) -> None:
        backoff = Backoff(self.backoff_min, self.backoff_max)
        while not self._stop.is_set():
            if self._port is None or self._broken.is_set():
                self._drop_port()
                try:
                    port = self._open()
                except Exception as exc:  # noqa: BLE001 - not there (yet): retry later
                    log.debug("serial open %s failed: %s", self.url, exc)
                    self._stop.wait(backoff.next())
                    continue
                if self._stop.is_set():
                    port.close()
                    break
                backoff.reset()
                self._set_port(port)
                log.info("serial port %s open", self.url)
            port = self._port
            try:
                data = port.read(port.in_waiting or 1)
            except Exception as exc:  # noqa: BLE001 - vanished port: reconnect
                if self._stop.is_set():
                    break
                log.warning("serial read failed: %s", exc)
                self._broken.set()
                continue
            if data:
                self._handle_bytes(data)

    def _handle_bytes(self, data: bytes) -> None:
        dec = self.decoder
        errors_before = dec.counters.errors
        frames = dec.feed(data)
        self.counters.rx_errors += dec.counters.errors - errors_before
        for frame in frames:
            self.counters.received += 1
            if self.on_frame is not None:
                try:
                    self.on_frame(frame)
                except Exception:
                    log.exception("on_frame hook failed")
            self._handle_frame(frame)

    def _handle_frame(self, frame: Frame) -> None:
        if wire.is_sensor_type(frame.type):
            self.unexpected += 1
            self.counters.rx_errors += 1
            return
        parsed = wire.parse_command(frame.type, frame.seq, frame.payload)
        if isinstance(parsed, Command):
            with self._lock:
                if len(self._commands) >= self._command_queue_size:
                    self._commands.popleft()
                    self.commands_dropped += 1
                self._commands.append(parsed)
            self._enqueue_ack(frame.seq, ResultCode.OK)
        else:
            seq, result = parsed
            self.counters.rx_errors += 1
            self._enqueue_ack(seq, result)

    # -- shutdown -------------------------------------------------------------------------

    def _close_internal(self) -> None:
        self._stop.set()
        with self._lock:
            self._lock.notify_all()
        self._writer_thread.join(timeout=0.5)
        self._io_thread.join(timeout=0.5)
        self._drop_port()

    def __repr__(self) -> str:
        state = "closed" if self.closed else ("connected" if self.connected else "disconnected")
        return f"SerialTransport({self.url!r}, {self.baudrate}, {state})"
