"""``optitac-edge layout``: a hexagonal array's layout CSV (docs/formats.md), for ``calibrate fibers --layout``."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from optitac_edge.cli.common import number

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    """``layout --rings R --pitch-mm P -o CSV``."""
    p = sub.add_parser("layout", help="write a hexagonal fiber array's layout CSV (a central fiber and rings)",
                       description="Write the layout CSV of a hexagonal array (docs/formats.md): a central fiber "
                                   "and RINGS rings at PITCH mm, rows along +x, numbered row by row from the top. "
                                   "Examples: --rings 8 --pitch-mm 1.5 (the paper's 217 fibers); --rings 4 "
                                   "--pitch-mm 4 (61 fibers); --rings 18 --pitch-mm 1.5 (1027 fibers).")
    p.add_argument("--rings", type=number(1, 60, integer=True), required=True, help="rings around the centre")
    p.add_argument("--pitch-mm", type=number(0.01, 100.0), required=True, help="centre-to-centre distance, mm")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="CSV")


def run(args: argparse.Namespace) -> int:
    from optitac_edge.core.layout import hex_layout
    from optitac_edge.io.layout_csv import save_layout_csv

    layout = hex_layout(args.rings, args.pitch_mm)
    save_layout_csv(layout, args.output)
    print(f"wrote {args.output}: {layout.n_fibers} fibers at {layout.pitch_mm:g} mm, "
          f"{2 * layout.radius_mm:g} mm across")
    return 0


def left(args: argparse.Namespace) -> str:
    """What an interrupted run left behind, for its one line."""
    return f"{args.output} not written (unchanged)"
