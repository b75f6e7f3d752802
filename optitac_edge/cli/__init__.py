"""The ``optitac-edge`` command line.

Every expected failure (bad recording, bad bundle, frames that don't match)
ends in one line on stderr and exit status 2; Ctrl-C ends a run with status 0.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Any

from optitac_edge import __version__
from optitac_edge.cli import bringup
from optitac_edge.cli.common import (
    COUNT,
    EXIT_ERROR,
    EXIT_INTERRUPTED,
    FPS,
    SEED,
    Parser,
    add_board,
    add_storage,
    board_config,
    frame_size,
    number,
    one_sensor_config,
)
from optitac_edge.cli.help import describe
from optitac_edge.errors import EXTRA_OF_MODULE, Interrupted, OptiTacError, missing_extra
from optitac_edge.io.logs import LIVE_LINE, NonBlockingLogging
from optitac_edge.text import fields

if TYPE_CHECKING:
    from typing_extensions import Self

log = logging.getLogger("optitac_edge")


def _add_orientation(p: argparse.ArgumentParser) -> None:
    p.add_argument("--rotation-deg", type=number(-360, 360), default=0.0, metavar="A",
                   help="the array appears rotated counter-clockwise by about A degrees in the image")
    p.add_argument("--mirror", action="store_true", help="the layout's x is negated before the rotation")


class _SimNames:
    """Names the simulator knows (``SCENARIOS`` or ``PHYSICS_NAMES``) as argparse choices, imported only when
    ``sim`` is parsed (or its help shown): every other command starts without the simulator and scipy."""

    def __init__(self, what: str) -> None:
        self._what = what

    def _names(self) -> tuple[str, ...]:
        if self._what == "physics":
            from optitac_edge.sim.physics import PHYSICS_NAMES

            return PHYSICS_NAMES
        from optitac_edge.sim.scenarios import SCENARIOS

        return SCENARIOS

    def __contains__(self, name: object) -> bool:
        return name in self._names()

    def __iter__(self) -> Iterator[str]:
        return iter(self._names())


def _add_fresh(p: argparse.ArgumentParser) -> None:
    p.add_argument("--fresh", action="store_true",
                   help="replace a complete recording at the output (it is kept until the new one is complete)")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="optitac-edge", description="OptiTac tactile sensor processing.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    _add_verbosity(parser, None)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)

    p = sub.add_parser("sim", help="write a recording from the built-in simulator")
    p.add_argument("out_dir", type=Path)
    p.add_argument("--scenario", required=True, choices=_SimNames("scenarios"), metavar="NAME", help="%(choices)s")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--frames", type=COUNT, default=None, help="number of frames (scenario default if omitted)")
    p.add_argument("--width", type=number(64, 8192, integer=True), default=640)
    p.add_argument("--height", type=number(64, 8192, integer=True), default=480)
    p.add_argument("--rgb", action="store_true", help="write (N,H,W,3) RGB frames")
    p.add_argument("--dark-fibers", type=str, default="", metavar="I,J,...",
                   help="layout indices of fibers that transmit no light")
    p.add_argument("--day", type=number(0, 10_000, integer=True), default=0,
                   help="session drift: camera shift, LED/pin gain, depth jitter, LED drift (0 = none)")
    p.add_argument("--variant", type=number(0, 10_000, integer=True), default=0,
                   help="another simulated sensor (optics and skin drawn from seed N; 0 = default); "
                        "sets its own rotation and mirror")
    p.add_argument("--physics", choices=_SimNames("physics"), default="default", metavar="NAME",
                   help="%(choices)s: the simulated skin's physics (docs/simulator.md); default: the simulator's own guess")
    p.add_argument("--warmup", type=number(-0.5, 0.5), default=0.03, help="LED change over a 'drift' recording")
    _add_fresh(p)
    add_storage(p, "raw", "raw (default): every frame as it is; fibers: the rest frames and each fiber's light")
    _add_orientation(p)
    add_board(p, default=None)  # --board B --sensor ID: the sensor's patch in whole frames of its sim camera

    cal = sub.add_parser("calibrate", help="calibration steps").add_subparsers(
        dest="step", required=True, parser_class=Parser)
    p = cal.add_parser("fibers", help="build a calibration bundle from a recording's rest frames")
    p.add_argument("recording", type=Path)
    p.add_argument("-o", "--output", type=Path, default=None, metavar="CAL",
                   help="the bundle to write (required, unless --sensor: that sensor's bundle)")
    add_board(p, default=None)
    p.add_argument("--layout", type=Path, default=None, metavar="CSV", help="custom layout (fiber,x_mm,y_mm)")
    _add_orientation(p)

    for step, text in (("orientation", ("check the fiber map against presses of known position; fix a "
                                        "rotation or mirror of the layout")),
                       ("centroid", "centroid error maps from presses of known position"),
                       ("width", "linear width model from circles of known diameter"),
                       ("shapes", "shape classifier from labelled presses"),
                       ("depth", "depth (and force, with a load cell's force_n column) from known depths")):
        p = cal.add_parser(step, help=text)
        p.add_argument("recording", type=Path)
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
            p.add_argument("--fill", choices=("auto", "nearest", "linear"), default="auto",
                           help="error between presses: auto (default) chooses by presses held out of the map; "
                                "the paper's nearest neighbour, or linear")

    p = sub.add_parser("evaluate", help="print accuracy metrics of a recording against its truth.csv")
    p.add_argument("recording", type=Path)
    p.add_argument("--cal", type=Path, required=True, metavar="CAL")
    p.add_argument("--shape-backend", choices=("numpy", "onnx"), default="numpy")
    p.add_argument("--onnx", type=Path, default=None, help="exported shape model for --shape-backend onnx")
    p.add_argument("--strict", action="store_true", help="exit 1 when the verdict is not good enough")

    p = sub.add_parser("export-onnx", help="export the bundle's shape classifier to ONNX")
    p.add_argument("cal", type=Path, metavar="CAL")
    p.add_argument("-o", "--output", type=Path, required=True)

    p = sub.add_parser("report", help="write calibration figures (PNG) and a summary")
    p.add_argument("cal", type=Path, metavar="CAL")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="DIR")
    p.add_argument("--unseen", type=Path, default=None, metavar="REC", help="recording for the unseen scatter")
    p.add_argument("--repeat", type=Path, default=None, metavar="REC", help="recording for repeatability")

    p = sub.add_parser("replay", help="process every frame of a recording into a contacts CSV")
    p.add_argument("recording", type=Path)
    p.add_argument("--cal", type=Path, required=True, metavar="CAL")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="CONTACTS.csv")

    p = sub.add_parser("run", help="capture -> process -> transmit (default: the built-in simulated sensor)")
    add_board(p)
    p.add_argument("--cal", type=Path, default=None, help="use this bundle (default: the board's)")
    p.add_argument("--serial", default=None, metavar="PORT", help="serial device or pyserial URL (overrides the board)")
    p.add_argument("--can", default=None, metavar="CHANNEL", help="CAN channel (overrides the board)")
    p.add_argument("--duration", type=number(0, 1e8, lo_open=True), default=None, metavar="S",
                   help="stop cleanly after S seconds")
    p.add_argument("--frames", type=COUNT, default=None, help="stop after N frames")
    p.add_argument("--fps", type=FPS, default=None, help="camera frame rate (overrides the board)")
    p.add_argument("--view", default=None, metavar="HOST:PORT",
                   help="serve the live view here (off by default; e.g. 127.0.0.1:8080, see docs/bring-up.md)")
    p.add_argument("--publish", default=None, metavar="zenoh[:CONFIG]",
                   help="publish every sensor's contacts and status on Zenoh as ROS 2 topics (rmw_zenoh), with "
                        "this Zenoh JSON5 config if given; 'none' turns the board's [publish.zenoh] off "
                        "(docs/network.md)")
    p.add_argument("--mcap", default=None, metavar="FILE",
                   help="also write every sensor's contacts and status to this MCAP file (rotation: [publish.mcap] "
                        "max_mb, max_minutes)")
    p.add_argument("--foxglove", default=None, metavar="HOST:PORT",
                   help="serve contacts, status, each sensor's image, surface and overlay live to Foxglove or "
                        "Lichtblick (e.g. 127.0.0.1:8765; needs the foxglove extra)")

    p = sub.add_parser("record", help="save frames of a live source as a recording")
    add_board(p)
    p.add_argument("-o", "--output", type=Path, required=True, metavar="REC")
    p.add_argument("--frames", type=COUNT, default=300)
    p.add_argument("--rest-frames", type=COUNT, default=10, help="leading contact-free frames (meta.json)")
    p.add_argument("--mcap", action="store_true",
                   help="write REC as one MCAP file (frames as sensor_msgs/Image; the default when REC ends in "
                        ".mcap); replay, calibrate and evaluate read it like a recording directory")
    _add_fresh(p)
    add_storage(p, None, "fibers (default for a directory): the rest frames and each fiber's light, ~0.4 kB a "
                          "frame; raw (an MCAP file's): every frame as it is")

    p = sub.add_parser("soak", help="run the full loop on the simulator with injected faults; report recovery")
    p.add_argument("--minutes", type=number(0, 1e6, lo_open=True), required=True, metavar="M")
    p.add_argument("--fault-rate", type=number(0, 1), default=0.01, metavar="R",
                   help="probability of a fault per read")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--fps", type=FPS, default=60.0)
    p.add_argument("--virtual-time", action="store_true",
                   help="service, camera and faults on a virtual clock: as fast as the machine computes, "
                        "same seed, same counts")

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
    p.add_argument("--patches", type=number(0, 16, integer=True), default=4, metavar="N",
                   help="paced runs: N patches of 217 fibers on one camera, every pipeline on each frame "
                        "(0: skip; gray only)")
    p.add_argument("--patch-frame", type=frame_size, default=(1280, 720), metavar="WxH",
                   help="the patches' camera frame (default 1280x720)")
    bringup.add_parsers(sub)
    _add_verbosity_to_commands(parser)
    describe(parser)
    return parser


def _add_verbosity(p: argparse.ArgumentParser, default: Any) -> None:
    """-v / -q, accepted before and after the command (``default`` SUPPRESS on the command's parser,
    so it keeps what was given before it)."""
    group = p.add_mutually_exclusive_group()
    group.add_argument("-v", "--verbose", action="count", default=0 if default is None else default,
                       help="more log detail (run: debug)")
    group.add_argument("-q", "--quiet", action="store_true", default=False if default is None else default,
                       help="warnings and errors only")


def _add_verbosity_to_commands(parser: argparse.ArgumentParser) -> None:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for command in dict.fromkeys(action.choices.values()):
                _add_verbosity(command, argparse.SUPPRESS)
                _add_verbosity_to_commands(command)


def _log_level(args: argparse.Namespace) -> int:
    """The service logs its life (INFO) unless -q; -v gives debug. Other commands: warnings, -v info."""
    if args.quiet:
        return logging.WARNING
    if args.command == "run":
        return logging.DEBUG if args.verbose else logging.INFO
    return logging.INFO if args.verbose == 1 else logging.DEBUG if args.verbose > 1 else logging.WARNING


def _board_sensor(args: argparse.Namespace) -> Any:
    """The board config narrowed to ``--sensor`` for an offline command (None without ``--board``)."""
    if args.board is None:
        if args.sensor is not None:
            raise OptiTacError("--sensor needs --board (the board config that lists the sensor)")
        return None
    return one_sensor_config(args)


def _cmd_sim(args: argparse.Namespace) -> int:
    from optitac_edge.core.layout import hex_layout
    from optitac_edge.sim.optics import CameraOptics
    from optitac_edge.sim.scenarios import write_scenario

    n_fibers = hex_layout().n_fibers
    try:
        dark = tuple(int(s) for s in args.dark_fibers.split(",") if s.strip())
    except ValueError:
        raise OptiTacError(f"--dark-fibers must be comma-separated integers, got {args.dark_fibers!r}") from None
    if any(not 0 <= i < n_fibers for i in dark) or len(set(dark)) != len(dark):
        raise OptiTacError(f"--dark-fibers must be distinct fiber indices in 0..{n_fibers - 1}")
    config = _board_sensor(args)
    patch = None
    if config is None:
        optics = CameraOptics(width=args.width, height=args.height, rgb=args.rgb,
                              rotation_deg=args.rotation_deg, mirror=args.mirror, dark_fibers=dark)
    else:
        optics, patch = _sim_board_sensor(args, config, dark)
    from optitac_edge.io.recording_paths import check_writable_recording

    check_writable_recording(args.out_dir, args.fresh)  # refused now, not after the simulation
    mcap = args.out_dir.suffix == ".mcap"
    out = args.out_dir.with_name(args.out_dir.name + ".dir.part") if mcap else args.out_dir
    if mcap:
        import shutil

        shutil.rmtree(out, ignore_errors=True)  # a conversion that did not finish
    if mcap and args.storage == "fibers":
        raise OptiTacError("--storage fibers: an MCAP recording holds raw frames (simulate into a directory)")
    path = write_scenario(out, args.scenario, seed=args.seed, frames=args.frames, optics=optics,
                          day=args.day, variant=args.variant, warmup=args.warmup, patch=patch,
                          fresh=args.fresh and not mcap, storage=args.storage, physics=args.physics)
    from optitac_edge.io.recording import read_meta

    sim_optics = read_meta(path / "meta.json").extra["simulator"]["optics"]
    if mcap:  # the recording, its times and truth in one MCAP file
        import shutil

        from optitac_edge.io.recording import Recording
        from optitac_edge.io.recording_mcap import recording_to_mcap

        try:
            path = recording_to_mcap(Recording(path), args.out_dir, replace=args.fresh)
        finally:
            shutil.rmtree(out, ignore_errors=True)
    mirror = " --mirror" if sim_optics["mirror"] else ""
    print(f"wrote {path} (orientation hint: --rotation-deg {sim_optics['rotation_deg']:.0f}{mirror})")
    return 0


def _sim_board_sensor(args: argparse.Namespace, config: Any, dark: tuple[int, ...]) -> tuple[Any, Any]:
    """``sim --board B --sensor ID``: the optics of the sensor as its simulated camera shows it, and its patch
    (None when it fills the frame). The camera sets size, pixel format and orientation: flags that would
    make another sensor are refused."""
    from optitac_edge.core.region import Region
    from optitac_edge.sim.optics import CameraOptics
    from optitac_edge.sim.patches import PatchFrames, PatchPlacement

    cam, name = config.camera, config.sensor.camera
    if cam.backend != "sim":
        raise OptiTacError(f"--board {args.board}: sensor {config.sensor.id}'s camera {name!r} is not simulated "
                           f"(backend {cam.backend!r})")
    given = [flag for flag, on in (("--width", args.width != 640), ("--height", args.height != 480),
                                   ("--rgb", args.rgb), ("--variant", args.variant != 0),
                                   ("--rotation-deg", args.rotation_deg != 0), ("--mirror", args.mirror)) if on]
    if given:
        raise OptiTacError(f"{', '.join(given)}: with --board the sensor's camera sets these")
    optics = CameraOptics(width=cam.width, height=cam.height, rgb=cam.pixel_format == "rgb", dark_fibers=dark)
    if not config.sensor.region:
        return optics, None
    regions = config.regions_of(name)
    frames = PatchFrames([Region(*r) for r in regions], cam.width, cam.height, optics=optics, seed=args.seed)
    return optics, PatchPlacement(frames, regions.index(config.sensor.region))


def _cmd_calibrate_fibers(args: argparse.Namespace) -> int:
    from optitac_edge.calibration.fibers import calibrate_fibers
    from optitac_edge.io.bundle_file import save_bundle
    from optitac_edge.io.layout_csv import load_layout_csv
    from optitac_edge.io.recording import Recording

    config = _board_sensor(args)
    output = args.output or (config.calibration.bundle_path if config is not None else None)
    if output is None:
        raise OptiTacError("calibrate fibers: give -o CAL (or --board B --sensor ID: that sensor's bundle)")
    rec = Recording(args.recording)
    layout_path = args.layout or (config.calibration.layout_path if config is not None else None)
    layout = load_layout_csv(layout_path) if layout_path else None
    region = config.sensor.region if config is not None else ()
    if region:
        from optitac_edge.calibration.region import Region, calibrate_region

        cam = config.camera
        if (rec.width, rec.height) != (cam.width, cam.height):
            raise OptiTacError(f"{args.recording}: frames are {rec.width}x{rec.height}, sensor "
                               f"{config.sensor.id}'s camera {config.sensor.camera!r} delivers "
                               f"{cam.width}x{cam.height}")
        bundle = calibrate_region(rec.rest_frames(), rec.pixel_format, Region(*region), layout=layout,
                                  rotation_hint_deg=args.rotation_deg, mirror=args.mirror)
    else:
        bundle = calibrate_fibers(rec.rest_frames(), rec.pixel_format, layout=layout,
                                  rotation_hint_deg=args.rotation_deg, mirror=args.mirror)
    bundle = save_bundle(bundle, output)
    report = bundle.fiber_map_report
    dead = [int(i) for i in bundle.layout.ids[bundle.fibers.dead]]
    placed = f" in region {list(region)}" if region else ""
    print(f"wrote {output} (id {bundle.calibration_id}){placed}: "
          f"{bundle.layout.n_fibers - len(dead)}/{bundle.layout.n_fibers} fibers found; "
          f"dead fibers {', '.join(map(str, dead)) or 'none'}; {len(bundle.fibers.unmatched_px)} unmatched blobs; "
          f"residual {report.get('residual_rms_px', float('nan')):.2f} px")
    return 0


def _step_bundle(args: argparse.Namespace) -> tuple[Path, Any]:
    """The bundle a calibration step updates: ``--cal``, or ``--sensor``'s (checked against its region)."""
    from optitac_edge.io.bundle_file import load_bundle

    config = _board_sensor(args)
    cal = args.cal or (config.calibration.bundle_path if config is not None else None)
    if cal is None:
        raise OptiTacError(f"calibrate {args.step}: give --cal CAL (or --board B --sensor ID: that sensor's bundle)")
    bundle = load_bundle(cal)
    if config is not None:
        from optitac_edge.service.bundles import check_bundle_region

        check_bundle_region(bundle, config.sensors[0], cal)
    return Path(cal), bundle


def _cmd_calibrate_model(args: argparse.Namespace) -> int:
    from optitac_edge.calibration import steps as calibrate_steps
    from optitac_edge.io.bundle_file import save_bundle
    from optitac_edge.io.recording import Recording

    rec = Recording(args.recording)
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
    if args.step == "shapes":
        bundle, summary = calibrate_steps.calibrate_shapes(rec, bundle, seed=args.seed)
    elif args.step == "depth":
        bundle, summary = calibrate_steps.calibrate_depth(rec, bundle)
    elif args.step == "centroid":
        bundle, summary = calibrate_steps.calibrate_centroid(rec, bundle, fill=args.fill,
                                                               bundle_path=str(args.cal))
    else:
        bundle, summary = calibrate_steps.calibrate_width(rec, bundle, kind=args.model)
    bundle = save_bundle(bundle, args.cal)
    print(f"updated {args.cal} (id {bundle.calibration_id}) with the {args.step} calibration: {fields(summary)}")
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from optitac_edge.calibration.evaluation import format_evaluation
    from optitac_edge.calibration.measure import measure_recording
    from optitac_edge.errors import RecordingError
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.recording import Recording

    rec = Recording(args.recording)
    if rec.truth is None:
        raise RecordingError(f"{rec.path}: evaluation needs truth.csv")
    bundle = load_bundle(args.cal)
    m = measure_recording(rec, bundle, shape_backend=args.shape_backend,
                          onnx_path=str(args.onnx) if args.onnx else None)
    from optitac_edge.calibration.verdict import judge

    print(f"{rec.path} with {args.cal} (id {bundle.calibration_id}):")
    for line in format_evaluation(m, rec.truth):
        print(line)
    verdict = judge(bundle, m, rec.truth)
    for line in verdict.lines():
        print(line)
    return 1 if args.strict and not verdict.good else 0


def _cmd_export_onnx(args: argparse.Namespace) -> int:
    from optitac_edge.core.corrections import load_shape_model
    from optitac_edge.errors import BundleError
    from optitac_edge.io.bundle_file import load_bundle

    model = load_shape_model(load_bundle(args.cal))
    if model is None:
        raise BundleError(f"{args.cal}: no shape model (run 'calibrate shapes' first)")
    from optitac_edge.calibration.onnx_export import export_onnx

    export_onnx(model, args.output)
    print(f"wrote {args.output}")
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from optitac_edge.calibration.report import write_report

    index = write_report(args.cal, args.output, unseen=args.unseen, repeat=args.repeat)
    print(f"wrote {index}")
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from optitac_edge.calibration.measure import replay_recording
    from optitac_edge.core.pipeline import Pipeline
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.contacts_csv import ContactsCsvWriter
    from optitac_edge.io.recording import Recording

    rec = Recording(args.recording)
    pipeline = Pipeline(load_bundle(args.cal))
    contacts = 0
    with ContactsCsvWriter(args.output) as out:
        for i, estimate in replay_recording(rec, pipeline):
            contacts += int(estimate.contact)
            out.write(i, estimate, int(rec.t_ns[i]))
    print(f"wrote {args.output}: {len(rec)} frames, {contacts} with contact")
    return 0


def _status_line(est: Any, fps: float | None) -> str:
    rate = "  -.- fps" if fps is None else f"{fps:5.1f} fps"
    if not est.baseline_ready:
        return f"{rate}  baselining..."
    if not est.contact:
        return f"{rate}  no contact"
    shape = f" {est.shape}" if est.shape else ""
    return (f"{rate}  CONTACT {est.x_mm:+.2f},{est.y_mm:+.2f} mm  {est.major_mm:.2f}x{est.minor_mm:.2f} mm  "
            f"{est.angle_deg:+.0f}°  s {est.strength:.0f}{shape}")


def _fps_overrides(args: argparse.Namespace) -> dict[str, float]:
    """``run --fps``: the frame rate of every camera of the board."""
    if args.fps is None:
        return {}
    from optitac_edge.config import load_board_config

    named = load_board_config(args.board, env=os.environ).named_cameras
    return {f"cameras.{name}.fps": args.fps for name in named} or {"camera.fps": args.fps}


def _publish_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """``--publish zenoh[:CONFIG]`` (or ``none``: the board's Zenoh off), ``--mcap FILE`` and ``--foxglove
    HOST:PORT`` as board config overrides of its ``[publish.NAME]``."""
    out: dict[str, Any] = {}
    value = getattr(args, "publish", None)
    if value is not None:
        backend, _, path = value.partition(":")
        if backend not in ("zenoh", "none") or (backend == "none" and path):
            raise OptiTacError(f"--publish must be zenoh, zenoh:CONFIG or none, got {value!r}")
        if backend == "none":
            out.update({"publish.zenoh": False, "publish.virtual": False})
        else:
            out.update({"publish.zenoh": True, **({"publish.zenoh.config": path} if path else {})})
    if getattr(args, "mcap", None):
        out["publish.mcap.path"] = args.mcap
    if getattr(args, "foxglove", None):
        out["publish.foxglove.bind"] = args.foxglove
    return out


def _cmd_run(args: argparse.Namespace) -> int:
    if args.duration is not None and not args.duration > 0:
        raise OptiTacError("--duration must be positive")
    link = {}
    if args.serial is not None:
        link = {"link.transport": "serial", "link.serial_url": args.serial}
    elif args.can is not None:
        link = {"link.transport": "can", "link.can_channel": args.can}
    config = board_config(args, **link, **_fps_overrides(args), **_publish_overrides(args))
    stop = threading.Event()
    received: list[int] = []

    def on_signal(signum: int, frame: object) -> None:  # Ctrl-C, systemd's stop, a closed terminal
        received.append(signum)
        stop.set()

    previous = {signum: signal.signal(signum, on_signal) for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    # run's own lines go to stdout through a queue too: a stdout nobody reads never holds up the service
    console = NonBlockingLogging(logging.INFO, sys.stdout, logger="optitac_edge.console", fmt="%(message)s",
                                 always=True).start()
    services: list[Any] = []
    try:
        say = logging.getLogger("optitac_edge.console").info
        services = _run_service(args, config, stop, say)
        several = len(services) > 1
        for service in services:
            stats = service.stats
            commands = " ".join(f"{k}={v}" for k, v in sorted(stats.commands.items())) or "none"
            # with several sensors on a camera, the contacts are each sensor's (below): a camera's frame is one
            contacts = f", {stats.contacts} with contact" if len(service.channels) == 1 else ""
            say("%sprocessed %d frames%s, dropped %d, camera errors %d, processing errors %d, commands %s",
                f"camera {service.camera_name}: " if several else "", stats.frames, contacts,
                stats.frames_dropped, stats.camera_errors, stats.processing_errors, commands)
            if len(config.sensors) > 1:
                for ch in service.channels:
                    say("  sensor %d %r: %d frames, %d with contact", ch.sensor_id, ch.name, ch.frames, ch.contacts)
        if services:
            say("%s", _link_summary(services[0].transport))
            network = service.network
            if network is not None:
                for ch in service.channels:
                    published, dropped = network.counters(ch.sensor_id)
                    say("  sensor %d %r: %d messages published, %d dropped (publishing errors %d; %s)",
                        ch.sensor_id, ch.name, published, dropped, network.errors, network.publisher.where)

        network = services[0].network if services else None
        for line in network.publisher.summary if network is not None else ():
            say("wrote %s", line)
    finally:
        console.stop()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if received and received[0] == signal.SIGINT:
        final = " (final STATUS sent)" if services and _delivered(services[0].transport) else ""
        print(f"optitac-edge: interrupted: the service stopped cleanly{final}", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0  # SIGTERM / SIGHUP: a requested stop (systemd counts it as success)


def _delivered(transport: Any) -> bool:
    """The link wrote something to the MCU (not the null link, not a port that never opened)."""
    return bool(transport.delivers and transport.counters.sent)


def _link_summary(transport: Any) -> str:
    """What went over the link: messages written and those that could not be (from the link's own counters;
    frames handed to a port that was never there are not "sent")."""
    if not transport.delivers:
        return "no link: nothing was sent"
    c = transport.counters
    stats = transport.stats() if hasattr(transport, "stats") else {}
    absent = " (the port was never open: is it plugged in, is the name right?)" \
        if not c.sent and not stats.get("connected", True) else ""
    return (f"link: {c.sent} messages written, {c.send_errors} not sent{absent}, {c.received} received, "
            f"{c.rx_errors} bad, {c.reconnects} reconnects")


class _StatusLine:
    """The live status line of ``run`` on a terminal, printed by its own thread: the frame loop only
    hands over a copy of the estimate when a line is due, and never waits on the terminal. The rate is
    over the last interval; the line is cut to the terminal's width so it never wraps."""

    def __init__(self, period_s: float, link: str, clock: Callable[[], int] = time.monotonic_ns,
                 label: str = "") -> None:
        self._clock = clock
        self._period_ns = int(period_s * 1e9)
        self._link = link
        self._label = label
        self._due_ns = 0
        self._last: tuple[int, int] | None = None  # (ns, frames) of the previous line
        self._latest: tuple[Any, float | None] | None = None
        self._stats: Any = None
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._print_loop, name="optitac-status-line", daemon=True)

    def offer(self, est: Any, stats: Any) -> None:
        """From the frame loop of the first camera that offers (the others' go by): keep a copy of ``est``
        when a line is due. One camera's counters make the rate (two cameras' made it -89.7 fps)."""
        if self._stats is None:
            self._stats = stats
        elif stats is not self._stats:
            return
        now = self._clock()
        if now < self._due_ns:
            return
        self._due_ns = now + self._period_ns
        fps = None
        if self._last is not None and now > self._last[0]:
            fps = (stats.frames - self._last[1]) * 1e9 / (now - self._last[0])
        self._last = (now, stats.frames)
        with self._lock:
            self._latest = (est.copy(), fps)
        self._wake.set()

    def _print_loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            with self._lock:
                latest, self._latest = self._latest, None
            if latest is not None:
                width = max(shutil.get_terminal_size((80, 24)).columns - 1, 20)
                line = f"[{self._link}] {self._label}{_status_line(*latest)}"
                with LIVE_LINE.lock:  # a log record clears the line first (it is drawn again here)
                    sys.stdout.write("\r\x1b[2K" + line[:width])
                    sys.stdout.flush()

    def __enter__(self) -> Self:
        LIVE_LINE.active = True
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=2.0)
        LIVE_LINE.active = False
        if not self._thread.is_alive():  # (a terminal stuck in write(): leave it alone)
            sys.stdout.write("\n")


def _run_service(args: argparse.Namespace, config: Any, stop: threading.Event,
                 say: Callable[..., None]) -> list[Any]:
    """Run the board's session; its services (the lead's first)."""
    from optitac_edge.service.session import BoardSession

    max_frames = args.frames
    link = "no link" if config.link.transport == "none" else config.link.transport
    with BoardSession(config, args.cal) as session, ExitStack() as stack:
        # a status line on a terminal only: a pipe or journald gets the log, and nothing that could block
        first = config.sensors[0]  # the lead camera's first sensor: the one the status line shows
        label = f"{first.sensor.name}: " if len(config.sensors) > 1 else ""
        line = stack.enter_context(_StatusLine(0.1, link, label=label)) if sys.stdout.isatty() else None
        if session.calibrates:
            say("calibrating fibers from the first rest frames...")
        bundle = session.bundle()
        if getattr(args, "view", None):
            url = session.open_view(args.view)
            say(f"view: {url}")
            _simulated_operator_for_the_view(session)
        via = link if link == "no link" else link + " link"
        if len(config.sensors) == 1:
            say(f"{int((~bundle.fibers.dead).sum())}/{bundle.layout.n_fibers} fibers; running "
                f"({config.camera.backend} camera, {via}; Ctrl-C to stop)")
        else:
            for name, group in session.bundles().items():
                for found in group:
                    b, where = found.bundle, list(found.sensor.sensor.region) or "the whole frame"
                    say(f"{found.sensor.label} on camera {name!r} ({where}): "
                        f"{int((~b.fibers.dead).sum())}/{b.layout.n_fibers} fibers")
            say(f"running {len(config.sensors)} sensors on {len(config.cameras)} camera(s) ({via}; Ctrl-C to stop)")

        def on_result(result: Any, stats: Any) -> None:
            if max_frames is not None and stats.frames >= max_frames:
                stop.set()
            if line is not None and stats is session.services[0].stats:  # the lead camera's first sensor
                line.offer(result.primary, stats)

        session.run(stop, duration_s=args.duration, on_result=on_result)
        return session.services


def _simulated_operator_for_the_view(session: Any) -> None:
    """On the simulated camera, a simulated operator does what the view's guided orientation asks (the
    simulator's own presses ignore its prompts)."""
    from optitac_edge.sim.camera import SimCamera
    from optitac_edge.sim.operator import PromptFollower

    if isinstance(session.camera, SimCamera) and session.view is not None:
        operator = PromptFollower(session.camera.sensor.layout.radius_mm)
        previous = session.camera.program

        def follow(prompt: str) -> None:
            operator.follow(prompt)
            session.camera.press_with(operator if prompt else previous)

        session.view.on_prompt = follow


def _cmd_record(args: argparse.Namespace) -> int:
    from optitac_edge.service.recorder import record_board

    mcap = args.mcap or args.output.suffix == ".mcap"
    if mcap and args.output.suffix != ".mcap":
        raise OptiTacError(f"--mcap: the recording's name must end in .mcap, got {args.output}")
    if mcap and args.storage == "fibers":
        raise OptiTacError("--storage fibers: an MCAP recording holds raw frames (record into a directory)")
    rec = record_board(one_sensor_config(args), args.output, args.frames, args.rest_frames, mcap=mcap,
                       replace=args.fresh, storage=args.storage or "fibers")
    print(f"wrote {args.output}: {rec.frames} frames of {rec.width}x{rec.height} {rec.pixel_format}")
    return 0


def _cmd_soak(args: argparse.Namespace) -> int:
    """The soak run (devtools.soak); one summary line, exit 1 if its verdict is FAILED."""
    from optitac_edge.devtools.soak import run_soak

    if not args.minutes > 0 or not 0 <= args.fault_rate <= 1:
        raise OptiTacError("--minutes must be positive and --fault-rate in 0..1")
    result = run_soak(args.minutes, fault_rate=args.fault_rate, seed=args.seed, fps=args.fps,
                      virtual_time=args.virtual_time)
    print(result.summary(), flush=True)
    return 0 if result.ok else 1


def _cmd_bench(args: argparse.Namespace) -> int:
    import json

    from optitac_edge.devtools.bench import format_table, run_bench
    from optitac_edge.io.files import check_output_path, write_file_atomic

    if args.frames < 1:
        raise OptiTacError("--frames must be >= 1")
    if not args.fps > 0:
        raise OptiTacError("--fps must be positive")
    from optitac_edge.io.cameras.frame_ring import MAX_DEPTH

    if args.queue_frames is not None and not 1 <= args.queue_frames <= MAX_DEPTH:
        raise OptiTacError(f"--queue-frames must be 1..{MAX_DEPTH}")
    check_output_path(args.json)  # refused now, not after minutes of measuring
    res = run_bench(frames=args.frames, source=args.source, fps=args.fps, cal=args.cal, rgb=args.rgb,
                    workdir=args.workdir, reference_frames=args.reference_frames,
                    memory_frames=args.memory_frames, e2e_seconds=args.e2e_seconds,
                    startup=not args.no_startup, queue_frames=args.queue_frames, view=args.view,
                    paced_frames=args.paced_frames, cpu_seconds=args.cpu_seconds, cpu_rounds=args.cpu_rounds,
                    e2e_contacts=args.e2e_contacts, patches=args.patches, patch_frame=args.patch_frame,
                    publish=args.e2e_publish, log=print)
    print(format_table(res))
    write_file_atomic(args.json, json.dumps(res, indent=1) + "\n")
    print(f"wrote {args.json}")
    return 0


def _left_after_interrupt(args: argparse.Namespace) -> str:
    """What an interrupted command left behind, for its one line."""
    command = args.command
    if command in ("sim", "record"):
        out = getattr(args, "out_dir", None) or args.output
        if getattr(args, "replacing", False):
            return f"recording {out} unchanged (the new one was not complete)"
        return f"recording {out} is incomplete (not usable; record it again)"
    if command == "calibrate":
        target = args.output if args.step == "fibers" else args.cal
        return f"bundle {target} unchanged"
    if command in ("replay", "export-onnx"):
        return f"{args.output} not written (unchanged)"
    if command == "report":
        return f"report {args.output} incomplete (index.md not updated)"
    if command == "bench":
        return f"{args.json} not written"
    if command == "soak":
        return "soak stopped early: no verdict"
    if command == "collect":
        if getattr(args, "replacing", False):
            return (f"tip retracted; recording {args.output} unchanged (the new collection in "
                    f"{args.output}.new is incomplete; --fresh starts it again)")
        return (f"tip retracted; recording {args.output} is incomplete: run the same command again to continue "
                "after the last complete press")
    if command == "orient":
        return "bundle unchanged"
    return "nothing written"


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``optitac-edge`` console script."""
    # One BLAS thread: the per-frame matrix-vector product is small, and worker
    # threads competing with the camera and link threads only add jitter.
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    parser = build_parser()
    args = parser.parse_args(argv)
    logs = NonBlockingLogging(_log_level(args)).start()  # nothing that logs ever waits on stderr
    handlers: dict[str, Callable[[argparse.Namespace], int]] = {
        "sim": _cmd_sim, "calibrate fibers": _cmd_calibrate_fibers, "calibrate centroid": _cmd_calibrate_model,
        "calibrate orientation": _cmd_calibrate_model,
        "calibrate width": _cmd_calibrate_model, "calibrate shapes": _cmd_calibrate_model,
        "calibrate depth": _cmd_calibrate_model,
        "evaluate": _cmd_evaluate, "export-onnx": _cmd_export_onnx, "report": _cmd_report, "replay": _cmd_replay,
        "run": _cmd_run, "record": _cmd_record, "soak": _cmd_soak, "bench": _cmd_bench,
        **bringup.HANDLERS}
    handler = handlers[f"{args.command} {args.step}" if args.command == "calibrate" else args.command]
    if getattr(args, "fresh", False):  # for the line an interrupt ends with: was a complete recording there?
        from optitac_edge.io.recording_paths import holds_recording

        args.replacing = holds_recording(Path(getattr(args, "out_dir", None) or args.output))
    message, code = None, EXIT_ERROR
    restore = {} if args.command == "run" else _interrupt_on_signals()  # run stops cleanly on its own
    try:
        code = handler(args)
    except OptiTacError as exc:
        message = f"error: {exc}"
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Interrupted) else signal.SIGINT
        by = "" if signum == signal.SIGINT else f" by {signal.Signals(signum).name}"
        message, code = f"interrupted{by}: {_left_after_interrupt(args)}", 128 + signum
    except OSError as exc:  # e.g. an output path that cannot be written
        where = f"{exc.filename}: " if exc.filename else ""
        message = f"error: {where}{exc.strerror or exc}"
    except ModuleNotFoundError as exc:  # an optional package this feature needs
        if exc.name is None or exc.name.split(".")[0] not in (*EXTRA_OF_MODULE, "picamera2"):
            raise
        message = f"error: {missing_extra(exc.name, f'optitac-edge {args.command}')}"
    except MemoryError:
        message = "error: out of memory"
    finally:
        logs.stop()  # the queued log lines first, then the verdict
        for signum, previous in restore.items():
            signal.signal(signum, previous)
    if message is not None:
        try:
            print(f"{chr(10) if code == EXIT_INTERRUPTED and sys.stderr.isatty() else ''}optitac-edge: {message}",
                  file=sys.stderr)
        except OSError:  # the terminal went with the SSH session
            pass
    return code


def _interrupt_on_signals() -> dict[int, Any]:
    """SIGINT, SIGTERM and SIGHUP raise :class:`Interrupted` (a KeyboardInterrupt) in the main thread, once:
    every command then cleans up as on Ctrl-C (``collect`` retracts the tip). A second signal during that
    cleanup is ignored, so it cannot cut a retract short. A signal ignored at start (``nohup``, a background
    job's SIGINT) stays ignored. Returns the handlers to restore."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    fired: list[int] = []

    def interrupt(signum: int, frame: object) -> None:
        if fired:
            return
        fired.append(signum)
        raise Interrupted(signum)

    previous: dict[int, Any] = {}
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(signum) is not signal.SIG_IGN:
            previous[signum] = signal.signal(signum, interrupt)
    return previous
