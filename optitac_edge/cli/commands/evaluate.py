"""``optitac-edge evaluate``: a bundle's accuracy on a recording with truth, and its verdict."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    """``evaluate RECORDING --cal CAL``."""
    p = sub.add_parser("evaluate", help="print accuracy metrics of a recording against its truth.csv")
    p.add_argument("recording", type=Path, nargs="+",
                   help="one or more recordings with truth.csv (directory or .mcap; days, sessions: each with its "
                        "own baseline), scored together")
    p.add_argument("--cal", type=Path, required=True, metavar="CAL")
    p.add_argument("--shape-backend", choices=("numpy", "onnx"), default="numpy")
    p.add_argument("--onnx", type=Path, default=None, help="exported shape model for --shape-backend onnx")
    p.add_argument("--strict", action="store_true", help="exit 1 when the verdict is not good enough")


def run(args: argparse.Namespace) -> int:
    from optitac_edge.calibration.evaluation import format_evaluation
    from optitac_edge.calibration.measure import measure_sessions, recordings_named
    from optitac_edge.errors import RecordingError
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.recording import Recording, refuse_repeated

    recs = [Recording(path) for path in args.recording]
    refuse_repeated(recs)
    for rec in recs:
        if rec.truth is None:
            raise RecordingError(f"{rec.path}: evaluation needs truth.csv")
    bundle = load_bundle(args.cal)
    m, truth = measure_sessions(recs, bundle, shape_backend=args.shape_backend,
                                onnx_path=str(args.onnx) if args.onnx else None)
    from optitac_edge.calibration.verdict import judge, levels_line

    print(f"{recordings_named(recs)} with {args.cal} (id {bundle.calibration_id}):")
    print(levels_line(bundle))
    for line in format_evaluation(m, truth, bundle.layout.pitch_mm):
        print(line)
    from optitac_edge.calibration.motion_report import format_motion, motion_report

    motion = motion_report(m, truth, recs[0].meta.fps) if len(recs) == 1 else None
    for line in format_motion(motion) if motion is not None else ():
        print(line)
    verdict = judge(bundle, m, truth)
    for line in verdict.lines():
        print(line)
    return 1 if args.strict and not verdict.good else 0
