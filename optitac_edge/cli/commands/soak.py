"""``optitac-edge soak``: the full loop on the simulator with injected faults, and its verdict."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from optitac_edge.cli.common import FPS, SEED, number
from optitac_edge.errors import OptiTacError

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    """``soak --minutes M``."""
    p = sub.add_parser("soak", help="run the full loop on the simulator with injected faults; report recovery")
    p.add_argument("--minutes", type=number(0, 1e6, lo_open=True), required=True, metavar="M")
    p.add_argument("--fault-rate", type=number(0, 1), default=0.01, metavar="R",
                   help="probability of a fault per read")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--fps", type=FPS, default=60.0)
    p.add_argument("--virtual-time", action="store_true",
                   help="service, camera and faults on a virtual clock: as fast as the machine computes, "
                        "same seed, same counts")


def run(args: argparse.Namespace) -> int:
    """The soak run (devtools.soak); one summary line, exit 1 if its verdict is FAILED."""
    from optitac_edge.devtools.soak import run_soak

    if not args.minutes > 0 or not 0 <= args.fault_rate <= 1:
        raise OptiTacError("--minutes must be positive and --fault-rate in 0..1")
    result = run_soak(args.minutes, fault_rate=args.fault_rate, seed=args.seed, fps=args.fps,
                      virtual_time=args.virtual_time)
    print(result.summary(), flush=True)
    return 0 if result.ok else 1


def left(args: argparse.Namespace) -> str:
    """What an interrupted run left behind, for its one line."""
    return "soak stopped early: no verdict"
