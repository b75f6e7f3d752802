"""The MCU's commands acted on: the link's state, the pipelines, the outboxes. No I/O, no logging."""

from __future__ import annotations

from collections.abc import Sequence
from enum import Enum

from optitac_edge.io.protocol.messages import Command, CommandType
from optitac_edge.io.protocol.outbox import LinkState
from optitac_edge.service.channel import SensorChannel


class Outcome(Enum):
    """What a command did, for the lead's log line."""

    DONE = "done"
    #: SET_PROTOCOL to another version than the link spoke.
    SWITCHED = "switched"
    #: SET_PROTOCOL for a version the link cannot speak: ignored.
    REFUSED = "refused"


def apply_command(command: Command, link: LinkState, channels: Sequence[SensorChannel],
                  protocols: Sequence[int]) -> Outcome:
    """Act on one validated command for every sensor of a camera.

    Parameters
    ----------
    command : Command
        Already acknowledged by the transport.
    link : LinkState
        Streaming, rate divider and protocol, set in place.
    channels : sequence of SensorChannel
        TARE re-takes each pipeline's baseline, SET_THRESHOLD sets its contact level, SET_PROTOCOL starts a new
        session of each outbox.
    protocols : sequence of int
        The versions the link can speak.
    """
    kind = command.type
    if kind == CommandType.TARE:
        for ch in channels:
            ch.pipeline.reset_baseline()
    elif kind == CommandType.STREAM:
        link.streaming = command.stream_on
        link.rate_divider = max(int(command.rate_divider), 1)
    elif kind == CommandType.SET_THRESHOLD:
        for ch in channels:
            ch.pipeline.set_contact_level(command.threshold_relative)
    elif kind == CommandType.SET_PROTOCOL:
        if command.version not in protocols:
            return Outcome.REFUSED
        switched = command.version != link.protocol
        link.protocol = command.version
        for ch in channels:
            ch.outbox.new_session()  # every contact is news to the MCU
        return Outcome.SWITCHED if switched else Outcome.DONE
    return Outcome.DONE
