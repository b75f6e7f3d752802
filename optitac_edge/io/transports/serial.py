"""Serial link to the gripper MCU: protocol v1 (docs/protocol.md) over a UART, USB CDC or pty.

Threads
-------
* the caller (the frame loop) only packs a payload and appends it to a bounded queue:
  :meth:`SerialTransport.send_contact` never blocks and never raises; when the queue is
  full the oldest frame is dropped and counted;
* a writer thread numbers (``seq``), frames and writes queued messages, ACKs first;
* an I/O thread owns the port: it opens it, reads and decodes incoming bytes, answers each
  command with an ACK, queues validated commands for :meth:`poll_commands`, and reopens the
  port with exponential backoff when it fails or vanishes (``counters.reconnects``).

The port is opened with ``serial.serial_for_url`` so ``loop://``, ``/dev/ttyUSB0`` and
pty slave paths all work.
"""

from __future__ import annotations

import errno
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from optitac_edge.errors import TransportError
from optitac_edge.io.protocol import wire
from optitac_edge.io.protocol.decoder import FrameDecoder
from optitac_edge.io.protocol.messages import Command, ContactMessage, ResultCode, StatusMessage
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

_IO_ERRORS: tuple[type[BaseException], ...] = (OSError,) if serial is None else (
    OSError, serial.SerialException)


class SerialTransport(Transport):
    """Protocol v1 over a serial port.

    Parameters
    ----------
    url : str
        Device path or pyserial URL (``/dev/ttyAMA0``, ``/dev/pts/3``, ``loop://``).
    baudrate : int
        921600 by default (8N1, no flow control).
    queue_size : int
        Outgoing CONTACT/STATUS frames kept while the writer is busy or the port is gone
        (oldest dropped when full); ACKs have their own queue of the same size.
    sensor_id : int
        0..255, written into every CONTACT and STATUS (overrides the messages' own).
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

    def __init__(self, url: str, baudrate: int = 921600, queue_size: int = 8, sensor_id: int = 0,
                 *, require_port: bool = True, read_timeout: float = 0.05,
                 write_timeout: float = 0.2, backoff_min: float = 0.05, backoff_max: float = 1.0,
                 on_frame: Callable[[Frame], None] | None = None,
                 command_queue_size: int = 32, open_port: Callable[[], Any] | None = None) -> None:
        super().__init__()
        if serial is None:
            raise TransportError("the serial transport needs pyserial (pip install pyserial)")
        if not 0 <= int(sensor_id) <= 255:
            raise TransportError(f"sensor_id {sensor_id} outside 0..255")
        if queue_size < 1:
            raise TransportError(f"queue_size must be >= 1, got {queue_size}")
        self.url = url
        self.baudrate = int(baudrate)
        self.sensor_id = int(sensor_id)
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

    # -- Transport API (frame loop side) --------------------------------------------------

    def send_contact(self, message: ContactMessage) -> None:
        """Queue one CONTACT; never blocks, never raises (drops are counted)."""
        try:
            payload = wire.contact_payload(message, self.sensor_id)
            self._enqueue(MsgType.CONTACT, int(message.t_us), payload)
        except Exception:
            log.exception("CONTACT not encodable")
            self.counters.send_errors += 1

    def send_status(self, message: StatusMessage) -> None:
        """Queue one STATUS; never blocks, never raises."""
        try:
            payload = wire.status_payload(message, self.sensor_id)
            self._enqueue(MsgType.STATUS, int(message.t_us), payload)
        except Exception:
            log.exception("STATUS not encodable")
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
            return len(self._queue) + len(self._acks)

    def stats(self) -> dict[str, Any]:
        """Every counter, flat (for STATUS and logs)."""
        c = self.counters
        out: dict[str, Any] = {
            "sent": c.sent, "send_errors": c.send_errors, "received": c.received,
            "rx_errors": c.rx_errors, "reconnects": c.reconnects, "dropped": self.dropped,
            "dropped_disconnected": self.dropped_disconnected, "unexpected": self.unexpected,
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
        with self._lock:
            if self._closed:
                return
            if len(self._queue) >= self._queue_size:
                self._queue.popleft()
                self.dropped += 1
                self.counters.send_errors += 1
            self._queue.append((msg_type, t_us & wire.U32, payload))
            self._lock.notify()

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
        """The next frame to write (ACKs first), popped; None if both queues are empty."""
        if self._acks:
            seq_acked, result = self._acks.popleft()
            t_us = (time.monotonic_ns() // 1000) & wire.U32
            return MsgType.ACK, t_us, wire.ACK.pack(seq_acked, result), ResultCode(result)
        if self._queue:
            msg_type, t_us, payload = self._queue.popleft()
            return msg_type, t_us, payload, None
        return None

    def _write_loop(self) -> None:
        drain_deadline: float | None = None
        while True:
            with self._lock:
                while not self._stop.is_set() and not (
                        (self._acks or self._queue) and self.connected):
                    if not self.connected and (self._acks or self._queue):
                        # keep the newest frames; they go out once the port is back
                        self._lock.wait(0.05)
                    else:
                        self._lock.wait(0.5)
                if self._stop.is_set():
                    if drain_deadline is None:
                        drain_deadline = time.monotonic() + 0.2
                    if not self.connected or time.monotonic() > drain_deadline:
                        return
                item = self._next()
                if item is None:
                    if self._stop.is_set():
                        return
                    continue
                self._writing = True
                seq = self._seq
                self._seq = (seq + 1) & wire.U16
            try:
                self._write_frame(item, seq)
            finally:
                self._writing = False

    def _write_frame(self, item: tuple[int, int, bytes, ResultCode | None], seq: int) -> None:
        msg_type, t_us, payload, ack_result = item
        data = wire.encode_frame(msg_type, seq, t_us, payload)
        port = self._port
        if port is None or self._broken.is_set():
            self.dropped_disconnected += 1
            self.counters.send_errors += 1
            return
        if self._resync:  # after (re)connecting or a partial write: end any partial frame
            data = wire.DELIMITER + data
            self._resync = False
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
        self._resync = True
        self._broken.clear()
        self._port = port
        with self._lock:
            self._lock.notify_all()

    def _drop_port(self) -> None:
        port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except Exception as exc:  # noqa: BLE001 - closing a vanished port may fail
                log.debug("closing %s: %s", self.url, exc)

    def _io_loop(self) -> None:
        backoff = self.backoff_min
        while not self._stop.is_set():
            if self._port is None or self._broken.is_set():
                self._drop_port()
                try:
                    port = self._open()
                except Exception as exc:  # noqa: BLE001 - not there (yet): retry later
                    log.debug("serial open %s failed: %s", self.url, exc)
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2, self.backoff_max)
                    continue
                if self._stop.is_set():
                    port.close()
                    break
                backoff = self.backoff_min
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
