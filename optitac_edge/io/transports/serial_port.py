"""Who owns the serial port: opening it, reading it, and reopening it with backoff when it fails or vanishes."""

from __future__ import annotations

import errno
import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from optitac_edge.errors import TransportError
from optitac_edge.io.backoff import Backoff
from optitac_edge.io.transports.base import TransportCounters
from optitac_edge.io.transports.serial_writer import FrameWriter

try:  # pyserial is needed only when this transport is used (lazy registry)
    import serial
except ImportError:  # pragma: no cover - reported when a SerialTransport is created
    serial = None

log = logging.getLogger(__name__)
#: errno of a port that is not there (yet): unplugged adapter, udev not done. Anything else is fatal at start.
_ABSENT = frozenset({errno.ENOENT, errno.ENODEV, errno.ENXIO, errno.EIO})
#: errno of a port another process holds (pyserial's exclusive flock).
_LOCKED = frozenset({errno.EAGAIN, errno.EWOULDBLOCK})
_IO_ERRORS: tuple[type[BaseException], ...] = (OSError,) if serial is None else (
    OSError, serial.SerialException)


def _errno(exc: BaseException) -> int | None:
    """The errno of an open failure (pyserial wraps the OSError and keeps its errno)."""
    return getattr(exc, "errno", None)


@dataclass(frozen=True)
class SerialTiming:
    """How long the port's reads and writes may take, and how fast a lost port is retried (seconds).

    ``read_timeout`` and ``write_timeout`` bound how long closing the link can take; reconnect
    delays double from ``backoff_min`` to ``backoff_max`` after each failed attempt.
    """

    read_timeout: float = 0.05
    write_timeout: float = 0.2
    backoff_min: float = 0.05
    backoff_max: float = 1.0


class PortKeeper:
    """Opens the port, reads it on the I/O thread (:meth:`run`) and reopens it when it fails.

    Parameters
    ----------
    url : str
        The port's name, for messages.
    open_port : callable
        Opens the port (``serial.serial_for_url`` with the link's settings, or a test's fake).
    writer : FrameWriter
        Told of every port opened and closed; its ``broken`` flag asks for a reopen.
    on_open : callable
        Called for every port opened, before the first read (the reader forgets old bytes).
    on_bytes : callable
        Called with every chunk read.
    counters : TransportCounters
        The link's counters (``reconnects``).
    timing : SerialTiming
        The reconnect delays.
    stop : threading.Event
        Set when the link closes: :meth:`run` returns.
    """

    def __init__(self, url: str, open_port: Callable[[], Any], writer: FrameWriter,
                 on_open: Callable[[], None], on_bytes: Callable[[bytes], None], counters: TransportCounters,
                 timing: SerialTiming, stop: threading.Event) -> None:
        self.url = url
        self._open_port = open_port
        self._writer = writer
        self._on_open = on_open
        self._on_bytes = on_bytes
        self._counters = counters
        self._timing = timing
        self._stop = stop
        self._ever_opened = False

    def open_first(self, require_port: bool) -> None:
        """Open the port at start. A bad URL, a port another process holds, or any failure but an absent port
        raises :class:`TransportError`; an absent one too when ``require_port``, else it is waited for."""
        url = self.url
        try:
            self._set_port(self._open_port())
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

    def _set_port(self, port: Any) -> None:
        if self._ever_opened:
            self._counters.reconnects += 1
        self._ever_opened = True
        self._on_open()
        self._writer.attach(port)

    def drop_port(self) -> None:
        """Close the port, if one is open (no write is under way on it when it closes)."""
        port = self._writer.detach()
        if port is not None:
            try:
                port.close()
            except Exception as exc:  # noqa: BLE001 - closing a vanished port may fail
                log.debug("closing %s: %s", self.url, exc)

    def run(self) -> None:
        """The I/O thread: (re)open the port with backoff, and read it, until the link stops."""
        backoff = Backoff(self._timing.backoff_min, self._timing.backoff_max)
        writer = self._writer
        while not self._stop.is_set():
            if writer.port is None or writer.broken.is_set():
                self.drop_port()
                try:
                    port = self._open_port()
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
            port = writer.port
            try:
                data = port.read(port.in_waiting or 1)
            except Exception as exc:  # noqa: BLE001 - vanished port: reconnect
                if self._stop.is_set():
                    break
                log.warning("serial read failed: %s", exc)
                writer.broken.set()
                continue
            if data:
                self._on_bytes(data)
