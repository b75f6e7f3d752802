"""CAN link to the gripper MCU: frames of ``optitac.dbc`` sent with python-can.

Every processed frame becomes two 8-byte frames, CONTACT_A and CONTACT_B, with
the same 4-bit rolling counter; STATUS has a counter of its own. Identifiers are
``base_id + 0x10 * sensor_id`` (+0 A, +1 B, +2 STATUS); one link carries every
sensor of a board, each on its own identifiers. Each sensor's outbox packs its
frames (:meth:`CanTransport.packer`, :class:`~optitac_edge.io.protocol.can_packer.CanPacker`);
the transport sends them. See docs/can.md.

A send never blocks and never raises: ``bus.send(..., timeout=0)``; a full
transmit queue (ENOBUFS), bus-off or any other CAN/OS error is counted in
``counters.send_errors`` and the frame dropped. Errors saying the interface is
gone (ENETDOWN, ENODEV, ...) or a long run of failures close the bus, and a
background thread reopens it with exponential backoff (``counters.reconnects``);
frames offered meanwhile are dropped and counted.
"""

from __future__ import annotations

import errno
import logging
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can

from optitac_edge.errors import TransportError
from optitac_edge.io.backoff import Backoff
from optitac_edge.io.protocol.can_codec import BASE_ID, CanCodec, message_ids
from optitac_edge.io.protocol.can_packer import CanPacker
from optitac_edge.io.protocol.packet import Packet
from optitac_edge.io.transports.base import Transport

if TYPE_CHECKING:
    from optitac_edge.io.device import BoardView
    from optitac_edge.io.transports.link import LinkConfig

log = logging.getLogger(__name__)

#: errnos meaning the interface is down or gone: close and reopen the bus.
LINK_DOWN_ERRNOS = frozenset({errno.ENETDOWN, errno.ENODEV, errno.ENXIO, errno.EBADF, errno.EIO,
                              errno.ENETUNREACH})
#: errnos of a full transmit queue (also what bus-off looks like on socketcan after a while).
QUEUE_FULL_ERRNOS = frozenset({errno.ENOBUFS, errno.EAGAIN})
#: What ``link.can_protocol`` may say: 1, 2 (v2's messages beside v1's) or 3 (and each contact's MOTION).
CAN_PROTOCOLS = (1, 2, 3)


@dataclass
class CanStats:
    """CAN-specific detail behind ``counters.send_errors`` / ``counters.reconnects``."""

    queue_full: int = 0  # ENOBUFS / EAGAIN / "Transmit buffer full"
    other_errors: int = 0  # any other CanError / OSError on send
    link_down: int = 0  # times the bus was declared down and closed
    dropped_link_down: int = 0  # frames dropped while the bus was closed
    open_failures: int = 0  # failed reopen attempts


def _errno_of(exc: BaseException) -> int | None:
    """The errno behind an OSError or a python-can error (``error_code``), if any."""
    code = getattr(exc, "errno", None)
    if code is None:
        code = getattr(exc, "error_code", None)
    if code is None and isinstance(exc.__cause__, OSError):
        code = exc.__cause__.errno
    return code if isinstance(code, int) else None


class CanTransport(Transport):
    """Sends CONTACT_A/B and STATUS frames on a python-can bus.

    Parameters
    ----------
    channel : str
        python-can channel (``can0``; any name for ``virtual``).
    interface : str
        python-can interface (``socketcan``, ``virtual``, ...).
    sensor_id : int or sequence of int
        The sensors the link carries (a board's several sensors share one bus); each message goes
        out on its own sensor's identifiers with that sensor's rolling counters. 0..79 with the
        default base id. A message of a sensor not listed is counted as a send error.
    bitrate : int, optional
        Passed to python-can when given (socketcan ignores it: set it with ``ip link``).
    dbc_path : str or Path, optional
        Database with the same message/signal names (default: the packaged ``optitac.dbc``).
    base_id : int
        Identifier of sensor 0's CONTACT_A (multiple of 0x10).
    backoff_s : tuple of float
        First and longest wait between reopen attempts, seconds.
    down_after : int
        This many failed sends in a row (e.g. bus-off filling the queue) also count as the
        link being down and make the transport reopen the bus.
    bus_kwargs : dict, optional
        Extra keyword arguments for ``can.Bus``.

    Raises
    ------
    TransportError
        A bad configuration or a bus that cannot be opened at construction.
    """

    def __init__(self, channel: str = "can0", interface: str = "socketcan", sensor_id: int | Sequence[int] = 0,  # noqa: PLR0913
                 bitrate: int | None = None, dbc_path: str | Path | None = None, *,
                 base_id: int = BASE_ID, backoff_s: tuple[float, float] = (0.1, 5.0),
                 down_after: int = 100, bus_kwargs: dict[str, Any] | None = None, protocol: int = 1) -> None:
        super().__init__()
        if protocol not in CAN_PROTOCOLS:
            raise TransportError(f"CAN protocol must be one of {CAN_PROTOCOLS}, got {protocol!r}")
        sensor_ids = [int(sensor_id)] if isinstance(sensor_id, int) else [int(i) for i in sensor_id]
        if not sensor_ids or len(set(sensor_ids)) != len(sensor_ids):
            raise TransportError(f"CAN link needs distinct sensor ids, got {sensor_ids}")
        self.codec = CanCodec(sensor_ids[0], dbc_path, base_id, protocol=protocol)
        #: Protocol 2: CONTACT2 and RELEASE frames on their own ids besides the v1 frames (a v1 MCU
        #: filters them out and never notices); 3: and a MOTION after each contact's CONTACT2 parts.
        self.from_start = frozenset(range(1, protocol + 1)) if protocol >= 2 else frozenset()
        #: The sensors the link carries.
        self.sensor_ids = tuple(sensor_ids)
        #: Each sensor's identifiers.
        self.sensor_can_ids = {sid: message_ids(sid, self.codec.base_id) for sid in sensor_ids}
        #: The first sensor's identifiers.
        self.ids = self.sensor_can_ids[sensor_ids[0]]
        self.channel, self.interface, self.bitrate = channel, interface, bitrate
        self.stats = CanStats()
        self._bus_kwargs = dict(bus_kwargs or {})
        self._backoff = Backoff(float(backoff_s[0]), float(backoff_s[1]))
        self._down_after = max(int(down_after), 1)
        self._consecutive_errors = 0
        self._lock = threading.Lock()  # guards _bus swaps and the reconnect thread
        self._send_lock = threading.Lock()  # several cameras' loops may send: counters stay exact
        self._stop = threading.Event()
        self._reconnector: threading.Thread | None = None
        try:
            self._bus: Any = self._open_bus()
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise TransportError(f"cannot open CAN {interface} channel {channel!r}: {exc}") from exc
        for sid, ids in self.sensor_can_ids.items():
            log.info("CAN %s/%s open: sensor %d, ids %s", interface, channel, sid,
                     ", ".join(f"{k}={v:#x}" for k, v in ids.items()))

    # -- bus handling -------------------------------------------------------------------------

    @classmethod
    def from_config(cls, section: LinkConfig, board: BoardView) -> CanTransport:
        """``[link] can_channel``, ``can_interface``, ``can_protocol``, ``can_bitrate`` (socketcan only)."""
        link = section
        return cls(channel=link.can_channel, interface=link.can_interface, sensor_id=list(board.sensor_ids),
                   protocol=link.can_protocol, bitrate=link.can_bitrate if link.can_interface == "socketcan" else None)

    def _open_bus(self) -> Any:
        kwargs = dict(self._bus_kwargs)
        if self.bitrate is not None:
            kwargs["bitrate"] = self.bitrate
        return can.Bus(channel=self.channel, interface=self.interface, **kwargs)

    @property
    def connected(self) -> bool:
        """True while a bus is open (False between a link failure and the reopen)."""
        return self._bus is not None

    def _link_down(self, bus: Any, reason: BaseException) -> None:
        """Close ``bus`` (if still current) and start reopening it in the background."""
        with self._lock:
            if self._bus is not bus or self._closed:
                return
            self._bus = None
            self.stats.link_down += 1
            self._consecutive_errors = 0
            if self._reconnector is None:
                self._reconnector = threading.Thread(target=self._reconnect_loop,
                                                     name="optitac-can-reconnect", daemon=True)
                self._reconnector.start()
        log.warning("CAN %s/%s down (%s); reopening in the background", self.interface, self.channel,
                    reason)
        self._shutdown_quietly(bus)

    def _reconnect_loop(self) -> None:
        while not self._stop.wait(self._backoff.next()):
            try:
                bus = self._open_bus()
            except Exception as exc:  # noqa: BLE001 - any driver failure means "try later"
                self.stats.open_failures += 1
                log.debug("CAN reopen failed: %s", exc)
                continue
            with self._lock:
                self._reconnector = None
                if not self._closed:
                    self._bus = bus
                    self.counters.reconnects += 1
                    bus = None
            if bus is not None:  # closed meanwhile
                self._shutdown_quietly(bus)
            else:
                log.info("CAN %s/%s reopened", self.interface, self.channel)
            return

    @staticmethod
    def _shutdown_quietly(bus: Any) -> None:
        try:
            bus.shutdown()
        except Exception as exc:  # noqa: BLE001 - a dying driver must not take the loop with it
            log.debug("CAN bus shutdown failed: %s", exc)

    # -- sending ------------------------------------------------------------------------------

    def _send(self, arbitration_id: int, payload: bytes) -> bool:
        """Send one frame without blocking; count and drop on any failure."""
        bus = self._bus
        if bus is None or self._closed:
            self.counters.send_errors += 1
            self.stats.dropped_link_down += 1
            return False
        frame = can.Message(arbitration_id=arbitration_id, data=payload, is_extended_id=False)
        try:
            bus.send(frame, timeout=0)
        except (can.CanError, OSError) as exc:
            self.counters.send_errors += 1
            self._consecutive_errors += 1
            code = _errno_of(exc)
            queue_full = code in QUEUE_FULL_ERRNOS or (code is None and "buffer full" in str(exc).lower())
            if queue_full:
                self.stats.queue_full += 1
            else:
                self.stats.other_errors += 1
            if self._consecutive_errors == 1:
                log.warning("CAN send failed (%s); dropping frames, counting", exc)
            if code in LINK_DOWN_ERRNOS or self._consecutive_errors >= self._down_after:
                self._link_down(bus, exc)
            return False
        self.counters.sent += 1
        if self._consecutive_errors:
            log.info("CAN sends recovered after %d failures", self._consecutive_errors)
        self._consecutive_errors = 0
        self._backoff.reset()
        return True

    def packer(self, sensor_id: int) -> CanPacker:
        """``sensor_id``'s frames on its identifiers with its rolling counters (the DBC through cantools).

        Raises
        ------
        TransportError
            If the link does not carry ``sensor_id``.
        """
        if sensor_id not in self.sensor_ids:
            raise TransportError(f"the CAN link carries sensors {', '.join(map(str, self.sensor_ids))}, "
                                 f"not {sensor_id}")
        return CanPacker(self.codec, sensor_id)

    def send(self, packet: Packet) -> None:
        """Send the packet's frames in turn without blocking. A frame after one that failed is not attempted
        (CONTACT_B without its CONTACT_A, a CONTACT2 part without the others, are useless) and counts as a
        send error too."""
        frames = packet.frames
        with self._send_lock:
            for k, (arbitration_id, data) in enumerate(frames):
                if not self._send(arbitration_id, data):
                    self.counters.send_errors += len(frames) - k - 1
                    return

    def _close_internal(self) -> None:
        self._stop.set()
        thread = self._reconnector
        if thread is not None and thread.is_alive() and thread is not threading.current_thread():
            thread.join(timeout=2.0)
        with self._lock:
            bus, self._bus = self._bus, None
        if bus is not None:
            self._shutdown_quietly(bus)


__all__ = ["LINK_DOWN_ERRNOS", "QUEUE_FULL_ERRNOS", "CanStats", "CanTransport"]
