"""Serial link to the gripper MCU: protocol v1 (docs/protocol.md) over a UART, USB CDC or pty.

Three parts, one per thread (read them in this order):

* :mod:`.serial_writer` (:class:`FrameWriter`): the frame loop's sends, which never block and
  never raise. It writes the frame itself when the line is idle, else it queues it for the
  writer thread, which writes ACKs first. ``seq`` is taken under one write lock, so the wire
  carries the frames in ``seq`` order.
* :mod:`.serial_reader` (:class:`CommandReader`): decodes incoming bytes, answers each command
  with an ACK and keeps the valid ones for :meth:`SerialTransport.poll_commands`.
* :mod:`.serial_port` (:class:`PortKeeper`): the I/O thread. It opens and reads the port, and
  reopens it with exponential backoff when it fails or vanishes (``counters.reconnects``).

The port is opened with ``serial.serial_for_url``, so ``loop://``, ``/dev/ttyUSB0`` and pty
slave paths all work.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from optitac_edge.errors import TransportError
from optitac_edge.io.protocol.messages import Command
from optitac_edge.io.protocol.packet import Packet
from optitac_edge.io.protocol.wire import Frame
from optitac_edge.io.threads import NamedThread
from optitac_edge.io.transports.base import Transport
from optitac_edge.io.transports.serial_port import PortKeeper, SerialTiming
from optitac_edge.io.transports.serial_reader import CommandReader
from optitac_edge.io.transports.serial_writer import FrameWriter

if TYPE_CHECKING:
    from optitac_edge.io.device import BoardView
    from optitac_edge.io.transports.link import LinkConfig

try:  # pyserial is needed only when this transport is used (lazy registry)
    import serial
except ImportError:  # pragma: no cover - reported when a SerialTransport is created
    serial = None

log = logging.getLogger(__name__)

__all__ = ["SerialTiming", "SerialTransport"]

_DEFAULT_TIMING = SerialTiming()


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
    timing : SerialTiming
        The port's read and write timeouts and the reconnect delays.
    on_frame : callable, optional
        Called from the I/O thread with every valid incoming :class:`Frame` (tests, tools).
    command_queue_size : int
        Validated commands kept for :meth:`poll_commands` (oldest dropped when full).
    open_port : callable, optional
        Opens the port (default: ``serial.serial_for_url`` of ``url`` with the timeouts
        above); a fake port or one a test unplugs goes in here.

    Attributes
    ----------
    writer : FrameWriter
        The sending side and its counters (``dropped``, ``acks``, ``direct_writes`` ...).
    reader : CommandReader
        The receiving side and its counters (``decoder.counters``, ``unexpected`` ...).
    """

    protocols = (1, 2, 3)

    def __init__(self, url: str, baudrate: int = 921600, queue_size: int = 8, *,
                 require_port: bool = True, timing: SerialTiming = _DEFAULT_TIMING,
                 on_frame: Callable[[Frame], None] | None = None,
                 command_queue_size: int = 32, open_port: Callable[[], Any] | None = None) -> None:
        super().__init__()
        if serial is None:
            raise TransportError("the serial transport needs pyserial (pip install pyserial)")
        if queue_size < 1:
            raise TransportError(f"queue_size must be >= 1, got {queue_size}")
        self.url = url
        self.baudrate = int(baudrate)
        self._stop = threading.Event()
        self.writer = FrameWriter(self.counters, queue_size, self._stop)
        self.reader = CommandReader(self.counters, self.writer.enqueue_ack, on_frame, command_queue_size)
        if open_port is None:
            # exclusive: a second process on the same port is refused (flock), not interleaved
            open_port = functools.partial(serial.serial_for_url, url, baudrate=self.baudrate,
                                          timeout=timing.read_timeout, write_timeout=timing.write_timeout,
                                          exclusive=True)
        self._keeper = PortKeeper(url, open_port, self.writer, self.reader.reset, self.reader.feed,
                                  self.counters, timing, self._stop)
        self._keeper.open_first(require_port)
        self._io_thread = NamedThread(target=self._keeper.run, name="optitac-serial-io", daemon=True)
        self._writer_thread = NamedThread(target=self.writer.run, name="optitac-serial-tx", daemon=True)
        self._io_thread.start()
        self._writer_thread.start()

    @classmethod
    def from_config(cls, section: LinkConfig, board: BoardView) -> SerialTransport:
        """``[link] serial_url``, ``baudrate``. A port that is not there yet (MCU unplugged, udev not done) is
        waited for, not fatal: the service streams as soon as it appears."""
        return cls(section.serial_url, baudrate=section.baudrate, require_port=False)

    # -- Transport API (frame loop side) --------------------------------------------------

    def send(self, packet: Packet) -> None:
        """Queue (or write) one packed message; never blocks, never raises (drops are counted)."""
        if not self._closed:
            self.writer.enqueue(packet.kind, packet.t_us, packet.frames[0][1])

    def poll_commands(self) -> list[Command]:
        """Validated commands received since the last call, oldest first (already ACKed)."""
        return self.reader.poll()

    @property
    def connected(self) -> bool:
        return self.writer.connected

    @property
    def pending(self) -> int:
        """Frames waiting in the send queues."""
        return self.writer.pending

    def stats(self) -> dict[str, Any]:
        """Every counter, flat (for STATUS and logs)."""
        c, w, r = self.counters, self.writer, self.reader
        out: dict[str, Any] = {
            "sent": c.sent, "send_errors": c.send_errors, "received": c.received,
            "rx_errors": c.rx_errors, "reconnects": c.reconnects, "dropped": w.dropped,
            "dropped_disconnected": w.dropped_disconnected, "unexpected": r.unexpected,
            "direct_writes": w.direct_writes, "partial_writes": w.partial_writes,
            "commands_dropped": r.commands_dropped, "connected": self.connected,
        }
        out.update({f"rx_{k}": v for k, v in r.decoder.counters.as_dict().items()})
        out.update({f"ack_{code.name.lower()}": n for code, n in w.acks.items()})
        return out

    def wait_idle(self, timeout: float = 1.0) -> bool:
        """Wait until the send queues are empty (tests, orderly shutdown); False on timeout."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.writer.pending == 0 and not self.writer.writing:
                return True
            time.sleep(0.002)
        return False

    def _close_internal(self) -> None:
        self._stop.set()
        self.writer.wake()
        self._writer_thread.join(timeout=0.5)
        self._io_thread.join(timeout=0.5)
        self._keeper.drop_port()

    def __repr__(self) -> str:
        state = "closed" if self.closed else ("connected" if self.connected else "disconnected")
        return f"SerialTransport({self.url!r}, {self.baudrate}, {state})"
