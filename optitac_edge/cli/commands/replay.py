"""``optitac-edge replay``: every frame of a recording into a contacts CSV, as the service would."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    """``replay RECORDING --cal CAL -o CSV``."""
    p = sub.add_parser("replay", help="process every frame of a recording into a contacts CSV")
    p.add_argument("recording", type=Path)
    p.add_argument("--cal", type=Path, required=True, metavar="CAL")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="CONTACTS.csv")


def run(args: argparse.Namespace) -> int:
    from optitac_edge.calibration.measure import replay_recording
    from optitac_edge.core.pipeline import Pipeline
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.contacts_csv import ContactsCsvWriter
    from optitac_edge.io.recording import Recording

    rec = Recording(args.recording)
    pipeline = Pipeline(load_bundle(args.cal), fps=rec.meta.fps)
    contacts = 0
    with ContactsCsvWriter(args.output) as out:
        for i, result in replay_recording(rec, pipeline):
            contacts += int(result.primary.contact)
            out.write(i, result)
    print(f"wrote {args.output}: {len(rec)} frames, {contacts} with contact")
    return 0


def left(args: argparse.Namespace) -> str:
    """What an interrupted run left behind, for its one line."""
    return f"{args.output} not written (unchanged)"
