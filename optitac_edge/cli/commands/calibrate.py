"""``optitac-edge calibrate STEP``: the calibration steps (fibers, orientation, centroid, width, shapes, depth)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from optitac_edge.cli.common import SEED, Parser, add_board, add_orientation, board_sensor
from optitac_edge.errors import OptiTacError
from optitac_edge.text import fields

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    """``calibrate STEP RECORDING``."""
    cal = sub.add_parser("calibrate", help="calibration steps").add_subparsers(
        dest="step", required=True, parser_class=Parser)
    p = cal.add_parser("fibers", help="build a calibration bundle from a recording's rest frames")
    p.add_argument("recording", type=Path)
    p.add_argument("-o", "--output", type=Path, default=None, metavar="CAL",
                   help="the bundle to write (required, unless --sensor: that sensor's bundle)")
    add_board(p, default=None)
    p.add_argument("--layout", type=Path, default=None, metavar="CSV", help="custom layout (fiber,x_mm,y_mm)")
    add_orientation(p, default=None)  # none given: a bundle replaced at -o keeps an orientation settled by presses

    for step, text in (("orientation", ("check the fiber map against presses of known position; fix a "
                                        "rotation or mirror of the layout")),
                       ("levels", ("contact levels and each fiber's band from rest and contact frames, chosen "
                                   "on held-out presses")),
                       ("centroid", "centroid error maps from presses of known position"),
                       ("width", "linear width model from circles of known diameter"),
                       ("shapes", "shape classifier from labelled presses"),
                       ("depth", "depth (and force, with a load cell's force_n column) from known depths")):
        p = cal.add_parser(step, help=text)
        p.add_argument("recording", type=Path, nargs="+",
                       help="one or more recordings with truth.csv (days, sessions: each with its own baseline)")
        p.add_argument("--cal", type=Path, default=None, metavar="CAL",
                       help="bundle to update in place (required, unless --sensor: that sensor's bundle)")
        add_board(p, default=None)
        if step == "shapes":
            p.add_argument("--seed", type=SEED, default=0, help="seed of the held-out split and the fits")
        if step == "width":
            p.add_argument("--model", choices=("auto", "linear", "monotone", "linear-radial", "monotone-radial"),
                           default="auto",
                           help="per-axis map: auto (default) chooses by presses held out of the fit; linear is "
                                "the paper's; -radial reads the width scaled by the distance from the centre")
        if step == "centroid":
            p.add_argument("--fill", choices=("auto", "nearest", "linear", "none"), default="auto",
                           help="error between presses: auto (default) chooses by presses held out of the map "
                                "(none: no map, where no map helps them); the paper's nearest neighbour, or linear")
            p.add_argument("--contacts", choices=("auto", "keep"), default="auto",
                           help="auto (default): one contact a frame where the presses show it places them "
                                "better than the configured several; keep: the configured count")


def run(args: argparse.Namespace) -> int:
    """``calibrate fibers`` builds a bundle; every other step updates one."""
    return _fibers(args) if args.step == "fibers" else _model(args)


def _fibers(args: argparse.Namespace) -> int:
    from optitac_edge.calibration.jobs import FiberMapJob, map_fibers

    config = board_sensor(args)
    output = args.output or (config.calibration.bundle_path if config is not None else None)
    if output is None:
        raise OptiTacError("calibrate fibers: give -o CAL (or --board B --sensor ID: that sensor's bundle)")
    region = camera = None
    if config is not None:  # a region comes from the board, for the frames of its camera
        region, cam = config.sensors[0].region, config.camera
        camera = (f"sensor {config.sensor.id}'s camera {config.sensor.camera!r}", cam.width, cam.height)
    layout = args.layout or (config.calibration.layout_path if config is not None else None)
    done = map_fibers(FiberMapJob(args.recording, Path(output), region, camera, layout and Path(layout),
                                  args.rotation_deg, args.mirror))
    bundle, report = done.bundle, done.bundle.fiber_map_report
    dead = [int(i) for i in bundle.layout.ids[bundle.fibers.dead]]
    placed = f" in region {[region.x, region.y, region.width, region.height]}" if region else ""
    stray = int(report.get("n_stray", 0))
    away = f" ({stray} away from the array: stray light, left out)" if stray else ""
    print(f"wrote {output} (id {bundle.calibration_id}){placed}: "
          f"{bundle.layout.n_fibers - len(dead)}/{bundle.layout.n_fibers} fibers found; "
          f"dead fibers {', '.join(map(str, dead)) or 'none'}; {len(bundle.fibers.unmatched_px)} unmatched blobs"
          f"{away}; residual {report.get('residual_rms_px', float('nan')):.2f} px")
    if done.kept:
        print(f"orientation kept: {output} had it settled by presses, and the new fiber map is turned as it was")
    elif done.lost:
        print(f"orientation not kept: {output} had it settled by presses, but the new fiber map is turned "
              f"otherwise; settle it again (orient, or calibrate orientation on presses)")
    return 0


def _model(args: argparse.Namespace) -> int:
    from optitac_edge.calibration.jobs import StepJob, run_step

    config = board_sensor(args)
    cal = args.cal or (config.calibration.bundle_path if config is not None else None)
    if cal is None:
        raise OptiTacError(f"calibrate {args.step}: give --cal CAL (or --board B --sensor ID: that sensor's bundle)")
    args.cal = Path(cal)  # (for the line of an interrupted run)
    job = StepJob(args.step, tuple(args.recording), args.cal, None if config is None else config.sensors[0].check_bundle,
                  seed=getattr(args, "seed", 0), width_model=getattr(args, "model", "auto"),
                  fill=getattr(args, "fill", "auto"), contacts=getattr(args, "contacts", "auto"))
    done = run_step(job)
    bundle, fit = done.bundle, done.fit
    if fit is None:
        print(f"updated {args.cal} (id {bundle.calibration_id}) with the {args.step} calibration: "
              f"{fields(done.summary)}")
        return 0
    assert fit.symmetry is not None
    other, other_rmse = fit.runner_up
    evidence = f"{fit.presses} presses, RMS {fit.best_rmse_mm:.2f} mm; next best '{other}' {other_rmse:.2f} mm"
    if fit.symmetry.is_identity:
        print(f"orientation of {args.cal} confirmed ({evidence})")
    else:
        print(f"corrected {args.cal} (id {bundle.calibration_id}): its fiber map was {fit.symmetry.label} "
              f"({evidence}); centroid, width and shape models were removed: calibrate them again")
    return 0


def left(args: argparse.Namespace) -> str:
    """What an interrupted run left behind, for its one line."""
    return "bundle " + str(args.output if args.step == "fibers" else args.cal) + " unchanged"
