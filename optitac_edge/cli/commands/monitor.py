"""``optitac-edge monitor``: what the MCU receives, and the MCU's commands sent."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from optitac_edge.cli.common import number
from optitac_edge.errors import OptiTacError

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    """``monitor --serial PORT | --can CHANNEL``."""
    p = sub.add_parser("monitor", help="show what the MCU receives (CONTACT, STATUS, ACK), rates, gaps, errors; "
                                       "send the MCU's commands")
    link = p.add_mutually_exclusive_group(required=True)
    link.add_argument("--serial", metavar="PORT", help="serial device or pyserial URL (the MCU's end of the link)")
    link.add_argument("--can", metavar="CHANNEL", help="CAN channel (e.g. can0)")
    p.add_argument("--baud", type=number(300, 4_000_000, integer=True), default=921600)
    p.add_argument("--can-interface", default="socketcan", help="python-can interface (default socketcan)")
    p.add_argument("--send", action="append", default=[], metavar="CMD",
                   help="send a command at start (serial): ping, tare, 'stream on [DIV]', 'stream off', "
                        "'threshold LEVEL', 'protocol 1|2|3' (SET_PROTOCOL: v2 sends CONTACT2 and RELEASE, v3 "
                        "also MOTION); repeatable")
    p.add_argument("--duration", type=number(0, 1e8, lo_open=True), default=None, metavar="S")
    p.add_argument("--all", action="store_true", help="print every message, not only a summary a second")


def run(args: argparse.Namespace) -> int:
    from optitac_edge.bringup.monitor import command_frame, monitor_can, monitor_serial, open_monitor_port

    def say(line: str) -> None:
        print(line, flush=True)

    if args.serial is not None:
        for text in args.send:
            command_frame(text, 0)  # refuse a bad command before opening anything
        monitor_serial(open_monitor_port(args.serial, args.baud), args.duration, args.send, say, every=args.all)
    else:
        if args.send:
            raise OptiTacError("protocol v1 carries no commands on CAN: --send needs --serial")
        monitor_can(args.can, args.can_interface, args.duration, say, every=args.all)
    return 0
