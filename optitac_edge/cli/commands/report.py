"""``optitac-edge report``: calibration figures and a summary."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    """``report CAL -o DIR``."""
    p = sub.add_parser("report", help="write calibration figures (PNG) and a summary")
    p.add_argument("cal", type=Path, metavar="CAL")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="DIR")
    p.add_argument("--unseen", type=Path, default=None, metavar="REC", help="recording for the unseen scatter")
    p.add_argument("--repeat", type=Path, default=None, metavar="REC", help="recording for repeatability")
    p.add_argument("--strict", action="store_true", help="exit 1 when the verdict is not good enough")


def run(args: argparse.Namespace) -> int:
    from optitac_edge.calibration.report import write_report

    written = write_report(args.cal, args.output, unseen=args.unseen, repeat=args.repeat)
    print(f"wrote {written.index}")
    print("\n".join(written.verdict.lines()))
    return 1 if args.strict and not written.verdict.good else 0


def left(args: argparse.Namespace) -> str:
    """What an interrupted run left behind, for its one line."""
    return f"report {args.output} incomplete (index.md not updated)"
