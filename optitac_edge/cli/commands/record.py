"""``optitac-edge record``: frames of a live source as a recording."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from optitac_edge.cli.common import COUNT, add_board, add_fresh, add_storage, one_sensor_config, recording_left
from optitac_edge.errors import OptiTacError

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    """``record -o REC``."""
    p = sub.add_parser("record", help="save frames of a live source as a recording")
    add_board(p)
    p.add_argument("-o", "--output", type=Path, required=True, metavar="REC")
    p.add_argument("--frames", type=COUNT, default=300)
    p.add_argument("--rest-frames", type=COUNT, default=10, help="leading contact-free frames (meta.json)")
    p.add_argument("--mcap", action="store_true",
                   help="write REC as one MCAP file (frames as sensor_msgs/Image; the default when REC ends in "
                        ".mcap); replay, calibrate and evaluate read it like a recording directory")
    add_fresh(p)
    add_storage(p, None, "fibers (default for a directory): the rest frames and each fiber's light, ~0.4 kB a "
                          "frame; raw (an MCAP file's): every frame as it is")


def run(args: argparse.Namespace) -> int:
    from optitac_edge.service.recorder import record_board

    mcap = args.mcap or args.output.suffix == ".mcap"
    if mcap and args.output.suffix != ".mcap":
        raise OptiTacError(f"--mcap: the recording's name must end in .mcap, got {args.output}")
    if mcap and args.storage == "fibers":
        raise OptiTacError("--storage fibers: an MCAP recording holds raw frames (record into a directory)")
    rec = record_board(one_sensor_config(args), args.output, args.frames, args.rest_frames, mcap=mcap,
                       replace=args.fresh, storage=args.storage or "fibers")
    pace = (f"{rec.span_s:.1f} s at {rec.meta.fps:g} fps; {rec.gaps} gaps ({rec.missing} frames missing), "
            f"{rec.dropped} dropped by the camera")
    print(f"wrote {args.output}: {rec.frames} frames of {rec.width}x{rec.height} {rec.pixel_format} over {pace}")
    if rec.missing or rec.dropped:
        print(f"warning: {rec.missing + rec.dropped} frames of the camera's {rec.meta.fps:g} fps are not in the "
              "recording (a busy machine or a slow disk?); its frame times say where", file=sys.stderr)
    return 0


left = recording_left
