"""``optitac-edge bench``: the per-frame loop measured (stages, reference, memory, end to end, start-up)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from optitac_edge.cli.common import COUNT, FPS, frame_size, number
from optitac_edge.errors import OptiTacError

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    """``bench [--frames N] ...``."""
    p = sub.add_parser("bench", help="measure the per-frame loop: stages, reference, memory, end to end, startup")
    p.add_argument("--frames", type=COUNT, default=20000, help="frames timed per stage (default 20000)")
    p.add_argument("--source", default="sim", metavar="sim|REC",
                   help="the simulated camera (default) or a recording directory")
    p.add_argument("--fps", type=FPS, default=240.0, help="frame rate of the end-to-end run (default 240)")
    p.add_argument("--cal", type=Path, default=None,
                   help="bundle to use (default: built once for the simulator with all calibration models)")
    p.add_argument("--rgb", action="store_true", help="simulated camera: RGB frames instead of gray")
    p.add_argument("--json", type=Path, default=Path("bench.json"), metavar="PATH",
                   help="write the results here (default bench.json)")
    p.add_argument("--workdir", type=Path, default=None, help="cache of the simulator bundle (default: a temp dir)")
    p.add_argument("--reference-frames", type=number(0, 10**7, integer=True), default=300,
                   help="frames the reference runs on (0: skip)")
    p.add_argument("--memory-frames", type=number(0, 10**8, integer=True), default=2000,
                   help="frames traced with tracemalloc (0: skip)")
    p.add_argument("--e2e-seconds", type=number(0, 1e6), default=60.0, help="end-to-end run length (0: skip)")
    p.add_argument("--no-startup", action="store_true", help="skip the start-to-first-packet run")
    p.add_argument("--queue-frames", type=int, default=None, metavar="N",
                   help="end to end: frames the camera queues for the loop (default: the sim board's "
                        "camera.queue_frames; 1 = latest frame only)")
    p.add_argument("--view", default=None, metavar="HOST:PORT",
                   help="end to end: serve the live view during the run (open it in a browser to include its cost)")
    p.add_argument("--paced-frames", type=number(0, 10**7, integer=True), default=2000, metavar="N",
                   help="frames per configuration of the paced runs: 0, 1, 2, 4 contacts and 217, 469, 1027 "
                        "fibers (0: skip)")
    p.add_argument("--cpu-seconds", type=number(0, 1e5), default=10.0, metavar="S",
                   help="service main-thread CPU: seconds per run with 0, 1, 2 and 4 contacts (0: skip)")
    p.add_argument("--cpu-rounds", type=number(1, 100, integer=True), default=2, metavar="R",
                   help="service main-thread CPU: interleaved passes over the contact counts (default 2)")
    p.add_argument("--e2e-publish", action="store_true",
                   help="end to end with every sensor's contacts, status and signal on Zenoh (to a subscriber "
                        "process on loopback) and in an MCAP file (needs the zenoh and mcap extras)")
    p.add_argument("--e2e-contacts", type=number(0, 4, integer=True), default=2, metavar="K",
                   help="end to end: indenters pressed throughout the run (default 2)")
    p.add_argument("--workers", type=number(0, 16, integer=True), default=None, metavar="W",
                   help="end to end with patches: the service's sensor worker threads (default: one per patch "
                        "beyond the first, as many as the cores beyond two)")
    p.add_argument("--patches", type=number(0, 16, integer=True), default=4, metavar="N",
                   help="paced runs: N patches of 217 fibers on one camera, every pipeline on each frame "
                        "(0: skip; gray only)")
    p.add_argument("--patch-frame", type=frame_size, default=(1280, 720), metavar="WxH",
                   help="the patches' camera frame (default 1280x720)")


def run(args: argparse.Namespace) -> int:
    import json

    from optitac_edge.devtools.bench import BenchPlan, format_table, run_bench
    from optitac_edge.io.files import check_output_path, write_file_atomic

    if args.frames < 1:
        raise OptiTacError("--frames must be >= 1")
    if not args.fps > 0:
        raise OptiTacError("--fps must be positive")
    from optitac_edge.io.cameras.frame_ring import MAX_DEPTH

    if args.queue_frames is not None and not 1 <= args.queue_frames <= MAX_DEPTH:
        raise OptiTacError(f"--queue-frames must be 1..{MAX_DEPTH}")
    check_output_path(args.json)  # refused now, not after minutes of measuring
    plan = BenchPlan(frames=args.frames, source=args.source, fps=args.fps, cal=args.cal, rgb=args.rgb,
                     workdir=args.workdir, reference_frames=args.reference_frames,
                     memory_frames=args.memory_frames, e2e_seconds=args.e2e_seconds,
                     startup=not args.no_startup, queue_frames=args.queue_frames, view=args.view,
                     paced_frames=args.paced_frames, cpu_seconds=args.cpu_seconds, cpu_rounds=args.cpu_rounds,
                     e2e_contacts=args.e2e_contacts, patches=args.patches, patch_frame=args.patch_frame,
                     publish=args.e2e_publish, workers=args.workers)
    res = run_bench(plan, log=print)
    print(format_table(res))
    write_file_atomic(args.json, json.dumps(res, indent=1) + "\n")
    print(f"wrote {args.json}")
    return 0


def left(args: argparse.Namespace) -> str:
    """What an interrupted run left behind, for its one line."""
    return f"{args.json} not written"
