"""The transport interface every link to the MCU implements: one :meth:`Transport.send` of a packed message."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING

from optitac_edge.io.device import BoardView, Device
from optitac_edge.io.protocol.messages import Command

if TYPE_CHECKING:  # the board config reads the registry without the wire format's packages (cobs)
    from typing_extensions import Self

    from optitac_edge.io.protocol.packet import Packer, Packet
    from optitac_edge.io.transports.link import LinkConfig


@dataclass
class TransportCounters:
    """What a link counts; bad data is counted, never trusted."""

    sent: int = 0
    send_errors: int = 0  # write failures, bus-off, ENOBUFS, queue overflow drops, messages not encodable
    received: int = 0  # valid incoming frames
    rx_errors: int = 0  # bad COBS, CRC, length, version, unknown or out-of-range commands
    reconnects: int = 0

    def send_error(self) -> None:
        """One more send error (a packer's callback for a message it could not encode)."""
        self.send_errors += 1


class Transport(Device, ABC):
    """A link to the gripper MCU: it ships the packets its own :meth:`packer` made (the outbox packs each
    sensor's messages where they are made). Never raises on a send: failures are counted.

    Use as a context manager; :meth:`close` is idempotent.
    """

    #: Messages go somewhere (False for :class:`NullTransport`, ``run`` without a link).
    delivers: bool = True
    #: The protocol versions the MCU may switch the link to (SET_PROTOCOL).
    protocols: tuple[int, ...] = (1,)
    #: The versions whose messages go out from the start whatever the MCU asked (CAN with
    #: ``link.can_protocol = 2``: {1, 2}; 3: {1, 2, 3}; the MCU cannot ask, and a v1 MCU filters the new ids
    #: out). Empty: only the version the MCU asked for (1 until it asks).
    from_start: frozenset[int] = frozenset()

    def __init__(self) -> None:
        self.counters = TransportCounters()
        Device.__init__(self)

    @classmethod
    def from_config(cls, section: LinkConfig, board: BoardView) -> Self:
        """Open it as a board's ``[link]`` ``section`` says, for the sensors of the ``board``. The default
        takes no keys."""
        return cls()

    def packer(self, sensor_id: int) -> Packer:
        """What packs ``sensor_id``'s messages for this link (the serial wire format by default; a message
        that cannot be encoded is a send error here)."""
        from optitac_edge.io.protocol.serial_packer import SerialPacker

        return SerialPacker(self.counters.send_error)

    @abstractmethod
    def send(self, packet: Packet) -> None:
        """Queue one packed message (non-blocking, never raising: failures are counted)."""

    def poll_commands(self) -> list[Command]:
        """Commands received since the last call (validated; bad ones already answered and counted)."""
        return []


class _NothingPacked:
    """The packer of a link that goes nowhere: no message is encoded (and no wire format imported)."""

    def contact(self, message: object) -> None:
        return None

    contact2 = release = motion = status = contact


class NullTransport(Transport):
    """Discards everything (``run`` without a link): nothing is packed, nothing sent."""

    delivers = False
    protocols = (1, 2, 3)

    def packer(self, sensor_id: int) -> Packer:
        """Nothing packed while the link delivers nothing (a subclass that delivers, such as a test's
        recorder, gets the serial wire format)."""
        return super().packer(sensor_id) if self.delivers else _NothingPacked()

    def send(self, packet: Packet) -> None:
        self.counters.sent += 1
