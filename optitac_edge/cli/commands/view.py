"""``optitac-edge view``: the live view in any browser."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from optitac_edge.cli.common import add_board, number

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    """``view [--bind HOST:PORT]``."""
    p = sub.add_parser("view", help="serve the live view: camera, fiber map, surface, contacts (any browser)")
    add_board(p)
    p.add_argument("--cal", type=Path, default=None, metavar="CAL", help="use this bundle (default: the board's)")
    p.add_argument("--bind", default="127.0.0.1:8080", metavar="HOST:PORT",
                   help="address to serve on (default 127.0.0.1:8080; anything else needs the printed token "
                        "for actions)")
    p.add_argument("--duration", type=number(0, 1e8, lo_open=True), default=None, metavar="S",
                   help="stop after S seconds")


def run(args: argparse.Namespace) -> int:
    """The service with the live view on ``--bind`` and no link."""
    from optitac_edge.cli.commands import run as run_command

    # a viewer at a terminal rides out a camera gap and says so (run under systemd exits to be restarted)
    run_args = argparse.Namespace(**vars(args), serial=None, can=None, frames=None, fps=None, view=args.bind,
                                  ride_out_stalls=True)
    return run_command.run(run_args)
