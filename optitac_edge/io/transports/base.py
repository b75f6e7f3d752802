"""The transport interface every link to the MCU implements."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from optitac_edge.io.device import Device
from optitac_edge.io.protocol.messages import (
    Command,
    ContactMessage,
    ContactV2Message,
    MotionMessage,
    ReleaseMessage,
    StatusMessage,
)


@dataclass
class TransportCounters:
    """What a link counts; bad data is counted, never trusted."""

    sent: int = 0
    send_errors: int = 0  # write failures, bus-off, ENOBUFS, queue overflow drops
    received: int = 0  # valid incoming frames
    rx_errors: int = 0  # bad COBS, CRC, length, version, unknown or out-of-range commands
    reconnects: int = 0


class Transport(Device, ABC):
    """A link to the gripper MCU. Never raises on a send: failures are counted.

    Use as a context manager; :meth:`close` is idempotent.
    """

    #: Messages go somewhere (False for :class:`NullTransport`, ``run`` without a link).
    delivers: bool = True
    #: The protocol versions the link can speak (the MCU switches with SET_PROTOCOL).
    protocols: tuple[int, ...] = (1,)
    #: Protocol v2's messages go out on their own ids beside v1's, from the start (CAN with
    #: ``link.can_protocol = 2``: the MCU cannot ask, and a v1 MCU filters the new ids out).
    v2_alongside_v1: bool = False
    #: Protocol v3's MOTION goes out beside v2's from the start (CAN with ``link.can_protocol = 3``).
    motion_alongside: bool = False

    def __init__(self) -> None:
        self.counters = TransportCounters()
        Device.__init__(self)

    @classmethod
    def from_link(cls, link: Any, sensor_ids: Sequence[int]) -> Transport:
        """Open it as a board's ``[link]`` section (``link``: its keys as attributes) says, for the board's
        ``sensor_ids``. The default takes no keys."""
        return cls()

    @abstractmethod
    def send_contact(self, message: ContactMessage) -> None:
        """Queue one CONTACT (non-blocking)."""

    @abstractmethod
    def send_status(self, message: StatusMessage) -> None:
        """Queue one STATUS (non-blocking)."""

    def send_contact_v2(self, message: ContactV2Message) -> None:
        """Queue one CONTACT2 (protocol v2, non-blocking); only called when 2 is in :attr:`protocols`
        or :attr:`v2_alongside_v1`."""
        raise NotImplementedError(f"{type(self).__name__} does not speak protocol v2")

    def send_release(self, message: ReleaseMessage) -> None:
        """Queue one RELEASE (protocol v2, non-blocking); only called when 2 is in :attr:`protocols`
        or :attr:`v2_alongside_v1`."""
        raise NotImplementedError(f"{type(self).__name__} does not speak protocol v2")

    def send_motion(self, message: MotionMessage) -> None:
        """Queue one MOTION (protocol v3, non-blocking); only called when 3 is in :attr:`protocols` or
        :attr:`motion_alongside`."""
        raise NotImplementedError(f"{type(self).__name__} does not speak protocol v3")

    def send(self, message: ContactMessage | ContactV2Message | ReleaseMessage | MotionMessage) -> None:
        """Queue one message of a sensor's frame (the outbox's), by its kind (non-blocking)."""
        if isinstance(message, ContactV2Message):
            self.send_contact_v2(message)
        elif isinstance(message, MotionMessage):
            self.send_motion(message)
        elif isinstance(message, ContactMessage):
            self.send_contact(message)
        else:
            self.send_release(message)

    def poll_commands(self) -> list[Command]:
        """Commands received since the last call (validated; bad ones already answered and counted)."""
        return []


class NullTransport(Transport):
    """Discards everything (``run`` without a link)."""

    delivers = False
    protocols = (1, 2, 3)

    def send_contact(self, message: ContactMessage) -> None:
        self.counters.sent += 1

    def send_contact_v2(self, message: ContactV2Message) -> None:
        self.counters.sent += 1

    def send_release(self, message: ReleaseMessage) -> None:
        self.counters.sent += 1

    def send_motion(self, message: MotionMessage) -> None:
        self.counters.sent += 1

    def send_status(self, message: StatusMessage) -> None:
        self.counters.sent += 1
