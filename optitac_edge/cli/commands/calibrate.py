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
    from optitac_edge.core.bundle import CalibrationBundle


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
    from optitac_edge.calibration.orientation import keep_orientation, settles
    from optitac_edge.calibration.sensor import calibrate_sensor
    from optitac_edge.core.layout import hex_layout
    from optitac_edge.io.bundle_file import save_bundle
    from optitac_edge.io.layout_csv import load_layout_csv
    from optitac_edge.io.recording import Recording

    config = board_sensor(args)
    output = args.output or (config.calibration.bundle_path if config is not None else None)
    if output is None:
        raise OptiTacError("calibrate fibers: give -o CAL (or --board B --sensor ID: that sensor's bundle)")
    rec = Recording(args.recording)
    layout_path = args.layout or (config.calibration.layout_path if config is not None else None)
    layout = load_layout_csv(layout_path) if layout_path else None
    region = config.sensors[0].region if config is not None else None
    # no hint given: a bundle at the output whose orientation presses settled gives it, and keeps it (below)
    previous = None if args.rotation_deg is not None or args.mirror else _readable_bundle(Path(output))
    settled = previous if previous is not None and settles(previous, layout or hex_layout()) else None
    hint = (args.rotation_deg or 0.0, args.mirror) if settled is None else (settled.transform.rotation_deg,
                                                                             settled.transform.mirror)
    if region and config is not None:  # a region comes from the board
        cam = config.camera
        if (rec.width, rec.height) != (cam.width, cam.height):
            raise OptiTacError(f"{args.recording}: frames are {rec.width}x{rec.height}, sensor "
                               f"{config.sensor.id}'s camera {config.sensor.camera!r} delivers "
                               f"{cam.width}x{cam.height}")
    bundle = calibrate_sensor(rec.rest_frames(), rec.pixel_format, region,
                              layout=layout, rotation_hint_deg=hint[0], mirror=hint[1],
                              times_ns=rec.t_ns[: rec.meta.rest_frames])
    kept = None if settled is None else keep_orientation(settled, bundle)
    bundle = save_bundle(bundle if kept is None else kept, output)
    report = bundle.fiber_map_report
    dead = [int(i) for i in bundle.layout.ids[bundle.fibers.dead]]
    placed = f" in region {[region.x, region.y, region.width, region.height]}" if region else ""
    stray = int(report.get("n_stray", 0))
    away = f" ({stray} away from the array: stray light, left out)" if stray else ""
    print(f"wrote {output} (id {bundle.calibration_id}){placed}: "
          f"{bundle.layout.n_fibers - len(dead)}/{bundle.layout.n_fibers} fibers found; "
          f"dead fibers {', '.join(map(str, dead)) or 'none'}; {len(bundle.fibers.unmatched_px)} unmatched blobs"
          f"{away}; residual {report.get('residual_rms_px', float('nan')):.2f} px")
    if kept is not None:
        print(f"orientation kept: {output} had it settled by presses, and the new fiber map is turned as it was")
    elif settled is not None:
        print(f"orientation not kept: {output} had it settled by presses, but the new fiber map is turned "
              f"otherwise; settle it again (orient, or calibrate orientation on presses)")
    return 0


def _readable_bundle(path: Path) -> CalibrationBundle | None:
    """The bundle at ``path``, or None (no file, or not a readable bundle: it is replaced as it is)."""
    from optitac_edge.io.bundle_file import load_bundle

    if not path.is_file():
        return None
    try:
        return load_bundle(path)
    except OptiTacError:
        return None


def _step_bundle(args: argparse.Namespace) -> tuple[Path, CalibrationBundle]:
    """The bundle a calibration step updates: ``--cal``, or ``--sensor``'s (checked against its region)."""
    from optitac_edge.io.bundle_file import load_bundle

    config = board_sensor(args)
    cal = args.cal or (config.calibration.bundle_path if config is not None else None)
    if cal is None:
        raise OptiTacError(f"calibrate {args.step}: give --cal CAL (or --board B --sensor ID: that sensor's bundle)")
    bundle = load_bundle(cal)
    if config is not None:
        config.sensors[0].check_bundle(bundle, cal)
    return Path(cal), bundle


def _model(args: argparse.Namespace) -> int:
    from optitac_edge.calibration import steps as calibrate_steps
    from optitac_edge.io.bundle_file import save_bundle
    from optitac_edge.io.recording import Recording

    rec = [Recording(path) for path in args.recording]
    args.cal, bundle = _step_bundle(args)
    if args.step == "orientation":
        bundle, fit = calibrate_steps.calibrate_orientation(rec, bundle)
        assert fit.symmetry is not None
        bundle = save_bundle(bundle, args.cal)
        other, other_rmse = fit.runner_up
        evidence = (f"{fit.presses} presses, RMS {fit.best_rmse_mm:.2f} mm; "
                    f"next best '{other}' {other_rmse:.2f} mm")
        if fit.symmetry.is_identity:
            print(f"orientation of {args.cal} confirmed ({evidence})")
        else:
            print(f"corrected {args.cal} (id {bundle.calibration_id}): its fiber map was {fit.symmetry.label} "
                  f"({evidence}); centroid, width and shape models were removed: calibrate them again")
        return 0
    if args.step == "levels":
        bundle, summary = calibrate_steps.calibrate_levels(rec, bundle)
    elif args.step == "shapes":
        bundle, summary = calibrate_steps.calibrate_shapes(rec, bundle, seed=args.seed)
    elif args.step == "depth":
        bundle, summary = calibrate_steps.calibrate_depth(rec, bundle)
    elif args.step == "centroid":
        bundle, summary = calibrate_steps.calibrate_centroid(rec, bundle, fill=args.fill,
                                                               bundle_path=str(args.cal), contacts=args.contacts)
    else:
        bundle, summary = calibrate_steps.calibrate_width(rec, bundle, kind=args.model)
    bundle = save_bundle(bundle, args.cal)
    print(f"updated {args.cal} (id {bundle.calibration_id}) with the {args.step} calibration: {fields(summary)}")
    return 0


def left(args: argparse.Namespace) -> str:
    """What an interrupted run left behind, for its one line."""
    return "bundle " + str(args.output if args.step == "fibers" else args.cal) + " unchanged"
