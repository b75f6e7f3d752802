"""``optitac-edge export-lerobot``: recordings as a LeRobot dataset, one episode each."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    """``export-lerobot REC [REC ...] --cal CAL -o DIR``."""
    p = sub.add_parser("export-lerobot", help="write recordings as a LeRobot dataset (one episode each)")
    p.add_argument("recording", type=Path, nargs="+", help="recordings of one sensor at one frame rate")
    p.add_argument("--cal", type=Path, required=True, metavar="CAL", help="the bundle the frames are replayed with")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="DIR", help="the dataset (a new directory)")
    p.add_argument("--repo-id", default="optitac/tactile", metavar="OWNER/NAME",
                   help="the dataset's name, as LeRobot's loader is given it (default optitac/tactile)")
    p.add_argument("--task", default="touch", help="the task of every frame (default: touch)")
    p.add_argument("--video", action="store_true",
                   help="add the tactile surface as a 224x224 video (observation.images.tactile)")


def run(args: argparse.Namespace) -> int:
    from optitac_edge.devtools.lerobot_export import ExportJob, export_lerobot
    from optitac_edge.errors import OptiTacError

    if "/" not in args.repo_id or args.repo_id.count("/") != 1 or not all(args.repo_id.split("/")):
        raise OptiTacError(f"--repo-id must be OWNER/NAME, got {args.repo_id!r}")
    job = ExportJob(tuple(args.recording), args.cal, args.output, args.repo_id, args.task, args.video)
    done = export_lerobot(job)
    per_k = done.seconds / max(done.frames, 1) * 1000
    print(f"wrote {args.output}: {done.episodes} episodes, {done.frames} frames, {done.bytes / 1e6:.1f} MB "
          f"in {done.seconds:.1f} s ({per_k:.2f} s per 1 000 frames)")
    return 0


def left(args: argparse.Namespace) -> str:
    """What an interrupted run left behind, for its one line."""
    return f"{args.output} not written"
