"""``optitac-edge collect``: an experiment on an indentation rig into a recording with truth."""

from __future__ import annotations

import argparse
import sys
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING

from optitac_edge.cli.common import add_board, add_storage, number, one_sensor_config
from optitac_edge.errors import OptiTacError
from optitac_edge.io.recording_paths import staging_path

if TYPE_CHECKING:
    from tqdm import tqdm
    from typing_extensions import Never

    from optitac_edge.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    """``collect EXPERIMENT``."""
    from optitac_edge.bringup.experiments import EXPERIMENTS

    p = sub.add_parser("collect", help="run an experiment on an indentation rig into a recording with truth")
    p.add_argument("experiment", choices=EXPERIMENTS, metavar="EXPERIMENT", help="%(choices)s")
    add_board(p)
    p.add_argument("--rig", default=None, metavar="URL",
                   help="gcode://PORT, ur://HOST or sim://?rotation=DEG&origin=X,Y (default: the board's rig.url)")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="REC")
    p.add_argument("--cal", type=Path, default=None, metavar="CAL",
                   help="bundle that reads the registration presses (default: the board's, or calibrated "
                        "from the first frames)")
    p.add_argument("--seed", type=number(0, 2**32 - 1, integer=True), default=0,
                   help="seed of the experiment's random positions")
    p.add_argument("--limit", type=number(1, 10**6, integer=True), default=None, metavar="N",
                   help="only N presses, spread over the whole experiment")
    p.add_argument("--fresh", action="store_true",
                   help="start again instead of continuing an interrupted collection; replaces a complete recording "
                        "at REC once the new one is complete")
    add_storage(p, "fibers", "fibers (default): the rest frames and each fiber's light, ~0.4 kB a frame; raw: "
                             "every frame as it is, ~300 kB a frame at 640x480")


def run(args: argparse.Namespace) -> int:

    from optitac_edge.bringup.collect import Collector
    from optitac_edge.bringup.rigs import open_rig
    from optitac_edge.io.recording_paths import check_writable_recording
    from optitac_edge.service.bundles import fiber_finder, obtain_bundle
    from optitac_edge.service.wiring import open_board_camera

    config = one_sensor_config(args)
    check_writable_recording(args.output, args.fresh)  # before anything opens or moves
    with ExitStack() as stack:
        rig, camera = open_rig(config, args.rig)
        stack.enter_context(rig)
        camera = stack.enter_context(camera if camera is not None else open_board_camera(config))
        bundle, _ = obtain_bundle(config, camera, args.cal)
        progress = PressProgress(args.experiment)
        stack.callback(progress.close)
        collector = Collector(camera, rig, bundle, prompt=lambda line: print(line, flush=True),
                              confirm=_wait_for_enter, storage=args.storage, find_fibers=fiber_finder(config))
        collector.progress = progress.update
        args.collecting = True  # from here on an interrupt retracts the tip (Collector.run), and says so
        result = collector.run(args.experiment, args.output, seed=args.seed, limit=args.limit, fresh=args.fresh)
    f = result.rig_frame
    print(f"wrote {args.output}: {result.experiment}, {result.presses} presses, {result.frames} frames"
          f"{f' (continued after press {result.resumed_at})' if result.resumed_at else ''}; "
          f"rig frame origin ({f.origin_xy_mm[0]:.2f}, {f.origin_xy_mm[1]:.2f}) mm, +x at {f.rotation_deg:+.2f}°, "
          f"surface z {f.surface_z_mm:.3f} mm; bundle orientation: {result.bundle_symmetry}")
    from optitac_edge.calibration.verdict import PRESSES_NEEDED

    if args.experiment in PRESSES_NEEDED:
        from optitac_edge.bringup.experiments import WIDTHS_MM

        model, need, at_least = PRESSES_NEEDED[args.experiment]
        at_least *= len(WIDTHS_MM) if args.experiment == "widths" else 1
        why = f"(it needs {need} for its held-out error to settle, docs/accuracy.md)"
        print(f"{result.presses} presses collected: too few for the {model} model {why}; evaluate's verdict will "
              "refuse it" if result.presses < at_least else
              f"{result.presses} presses collected: enough for the {model} model {why}")
    return 0


def _wait_for_enter(line: str) -> None:

    print(line, flush=True)
    if sys.stdin.readline() == "":
        raise OptiTacError("standard input closed while waiting for the operator")


def _left(elapsed_s: float, timed: int, left: int) -> str:
    """'; about N min left' at the pace of the ``timed`` presses timed so far ("" before one was timed: the
    clock starts when the first press is done, its time holding the setup and touch-off)."""
    if timed < 1 or left < 1:
        return ""
    minutes = elapsed_s / timed * left / 60
    return "; under a minute left" if minutes < 1 else f"; about {minutes:.0f} min left"


class PressProgress:
    """Presses done of all, and the time left at the pace so far: a bar on a terminal (tqdm), else a line a press
    (a log, journald)."""

    def __init__(self, experiment: str) -> None:
        self.experiment = experiment
        self._bar: tqdm[Never] | None = None  # a bar counted by hand, over no iterable
        self._started: float | None = None

    def update(self, done: int, total: int) -> None:
        import time

        now = time.monotonic()
        if self._started is None:
            self._started, self._first = now, done - 1  # a continued collection starts after its done presses
        if sys.stdout.isatty():
            if self._bar is None:
                from tqdm import tqdm

                self._bar = tqdm(total=total, initial=done - 1, desc=self.experiment, unit="press", leave=False)
            self._bar.update(1)
            return
        print(f"press {done} of {total} done{_left(now - self._started, done - self._first - 1, total - done)}",
              flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


def left(args: argparse.Namespace) -> str:
    """What an interrupted collection left behind (the tip is retracted first), for its one line."""
    if not getattr(args, "collecting", False):  # the rig, camera or bundle were still opening
        return f"nothing moved and nothing was recorded (interrupted while starting; {args.output} unchanged)"
    if getattr(args, "replacing", False):
        if not staging_path(Path(args.output)).exists():  # the signal came as the new one took its place
            return f"tip retracted; recording {args.output} replaced by the new collection (complete)"
        return (f"tip retracted; recording {args.output} unchanged (the new collection in "
                f"{args.output}.new is incomplete; --fresh starts it again)")
    return (f"tip retracted; recording {args.output} is incomplete: run the same command again to continue "
            "after the last complete press")
