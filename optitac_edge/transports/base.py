"""The transport interface every link to the MCU implements."""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass

from ..messages import Command, ContactMessage, StatusMessage


@dataclass
class TransportCounters:
    """What a link counts; bad data is counted, never trusted."""

    sent: int = 0
    send_errors: int = 0  # write failures, bus-off, ENOBUFS, queue overflow drops
    received: int = 0  # valid incoming frames
    rx_errors: int = 0  # bad COBS, CRC, length, version, unknown or out-of-range commands
    reconnects: int = 0


class Transport(ABC):
    """A link to the gripper MCU. Never raises on a send: failures are counted.

    Use as a context manager; :meth:`close` is idempotent.
    """

    def __init__(self) -> None:
        self.counters = TransportCounters()
        self._closed = False
        self._close_lock = threading.Lock()

    @abstractmethod
    def send_contact(self, message: ContactMessage) -> None:
        """Queue one CONTACT (non-blocking)."""

    @abstractmethod
    def send_status(self, message: StatusMessage) -> None:
        """Queue one STATUS (non-blocking)."""

    def poll_commands(self) -> list[Command]:
        """Commands received since the last call (validated; bad ones already answered and counted)."""
        return []

    def _close_internal(self) -> None:  # noqa: B027 - optional hook
        """Release the device; called once."""

    def close(self) -> None:
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
        self._close_internal()

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> Transport:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class NullTransport(Transport):
    """Discards everything (``run`` without a link)."""

    def send_contact(self, message: ContactMessage) -> None:
        self.counters.sent += 1

    def send_status(self, message: StatusMessage) -> None:
        self.counters.sent += 1
