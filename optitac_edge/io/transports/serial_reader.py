"""The receiving side of the serial link: bytes in, validated commands out, each answered with an ACK."""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable

from optitac_edge.io.protocol import wire
from optitac_edge.io.protocol.decoder import FrameDecoder
from optitac_edge.io.protocol.messages import Command, CommandType, ResultCode
from optitac_edge.io.protocol.wire import Frame
from optitac_edge.io.transports.base import TransportCounters

log = logging.getLogger(__name__)


class CommandReader:
    """Decodes what the MCU sends and keeps its validated commands for the frame loop.

    Every incoming command is answered (``ack(seq, result)``): OK when it is valid and kept,
    its refusal code when not (counted in ``counters.rx_errors``). Frames of a type the sensor
    itself sends (an echo, crossed wires) are dropped unanswered.

    Parameters
    ----------
    counters : TransportCounters
        The link's counters (``received``, ``rx_errors``), shared with the transport.
    ack : callable
        ``ack(seq_acked, result)`` queues the answer to one incoming frame.
    on_frame : callable, optional
        Called with every valid incoming :class:`Frame` (tests, tools).
    queue_size : int
        Validated commands kept for :meth:`poll` (oldest dropped when full).
    """

    def __init__(self, counters: TransportCounters, ack: Callable[[int, int], None],
                 on_frame: Callable[[Frame], None] | None = None, queue_size: int = 32) -> None:
        self.counters = counters
        self.decoder = FrameDecoder()
        self.on_frame = on_frame
        #: valid frames of a type the sensor sends (echo, crossed wires), dropped unanswered
        self.unexpected = 0
        #: commands answered BUSY: the command queue was full of state-changing commands (loop not polling)
        self.commands_dropped = 0
        self._ack = ack
        self._lock = threading.Lock()
        self._commands: deque[Command] = deque()
        self._queue_size = int(queue_size)

    def reset(self) -> None:
        """A new port: forget any partial frame of the old one."""
        self.decoder.reset()

    def feed(self, data: bytes) -> None:
        """Decode a chunk of bytes (any chunking) and handle each frame in it."""
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

    def poll(self) -> list[Command]:
        """Validated commands received since the last call, oldest first (already ACKed)."""
        with self._lock:
            out = list(self._commands)
            self._commands.clear()
        return out

    def _queue(self, command: Command) -> bool:
        """Queue ``command`` for the service loop (holding ``_lock``); False: no room (answer BUSY).

        A state-changing command is never dropped: on a full queue a PING gives way (it has no state: its ACK
        is its answer), else the new command is refused, never an older one taken out after its ACK.
        """
        if len(self._commands) >= self._queue_size:
            ping = next((k for k, c in enumerate(self._commands) if c.type == CommandType.PING), None)
            if ping is None:
                if command.type == CommandType.PING:
                    return True  # acknowledged: all a PING asks
                self.commands_dropped += 1
                return False
            del self._commands[ping]
        self._commands.append(command)
        return True

    def _handle_frame(self, frame: Frame) -> None:
        if wire.is_sensor_type(frame.type):
            self.unexpected += 1
            self.counters.rx_errors += 1
            return
        parsed = wire.parse_command(frame.type, frame.seq, frame.payload)
        if isinstance(parsed, Command):
            with self._lock:
                queued = self._queue(parsed)
            self._ack(frame.seq, ResultCode.OK if queued else ResultCode.BUSY)
        else:
            seq, result = parsed
            self.counters.rx_errors += 1
            self._ack(seq, result)
