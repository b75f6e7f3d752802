"""Bring-up commands: ``orient`` (and, as they come, ``collect``, ``monitor``, ``view``, ``snapshot``)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import Any

from optitac_edge.cli.common import add_board, add_storage, number, one_sensor_config
from optitac_edge.errors import OptiTacError


def add_parsers(sub: Any) -> None:
    """Add the bring-up commands to the ``optitac-edge`` subparsers ``sub``."""
    p = sub.add_parser("orient", help="find the layout's orientation from two presses (+x edge, then +y edge) "
                                      "and write it into the bundle")
    add_board(p)
    p.add_argument("--cal", type=Path, default=None, metavar="CAL",
                   help="bundle to check and correct (default: the board's)")
    p.add_argument("-o", "--output", type=Path, default=None, metavar="CAL",
                   help="write the oriented bundle here (default: where it was read from)")
    p.add_argument("--timeout", type=number(1, 3600), default=120.0, metavar="S",
                   help="give up after S seconds of camera time (default 120)")
    _add_collect(sub)

    p = sub.add_parser("monitor", help="show what the MCU receives (CONTACT, STATUS, ACK), rates, gaps, errors; "
                                       "send the MCU's commands")
    link = p.add_mutually_exclusive_group(required=True)
    link.add_argument("--serial", metavar="PORT", help="serial device or pyserial URL (the MCU's end of the link)")
    link.add_argument("--can", metavar="CHANNEL", help="CAN channel (e.g. can0)")
    p.add_argument("--baud", type=number(300, 4_000_000, integer=True), default=921600)
    p.add_argument("--can-interface", default="socketcan", help="python-can interface (default socketcan)")
    p.add_argument("--send", action="append", default=[], metavar="CMD",
                   help="send a command at start (serial): ping, tare, 'stream on [DIV]', 'stream off', "
                        "'threshold LEVEL', 'protocol 1|2' (SET_PROTOCOL: v2 sends CONTACT2 and RELEASE); repeatable")
    p.add_argument("--duration", type=number(0, 1e8, lo_open=True), default=None, metavar="S")
    p.add_argument("--all", action="store_true", help="print every message, not only a summary a second")

    p = sub.add_parser("view", help="serve the live view: camera, fiber map, surface, contacts (any browser)")
    add_board(p)
    p.add_argument("--cal", type=Path, default=None, metavar="CAL", help="use this bundle (default: the board's)")
    p.add_argument("--bind", default="127.0.0.1:8080", metavar="HOST:PORT",
                   help="address to serve on (default 127.0.0.1:8080; anything else needs the printed token "
                        "for actions)")
    p.add_argument("--duration", type=number(0, 1e8, lo_open=True), default=None, metavar="S",
                   help="stop after S seconds")

    p = sub.add_parser("snapshot", help="write the live view's picture of a board's camera to a PNG")
    add_board(p)
    p.add_argument("--cal", type=Path, default=None, metavar="CAL", help="use this bundle (default: the board's)")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="PNG")
    p.add_argument("--frames", type=number(1, 10**5, integer=True), default=10,
                   help="frames processed after the baseline before the picture (default 10)")


def _add_collect(sub: Any) -> None:
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


def _cmd_collect(args: argparse.Namespace) -> int:
    from contextlib import ExitStack

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
        collector = Collector(camera, rig, bundle, prompt=lambda line: print(line, flush=True),
                              confirm=_wait_for_enter, storage=args.storage, find_fibers=fiber_finder(config))
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
        print(f"the {model} model needs {need} for its held-out error to settle (docs/accuracy.md); "
              f"{result.presses} presses collected" + (": too few, evaluate's verdict will refuse the model"
                                                        if result.presses < at_least else ""))
    return 0


def _wait_for_enter(line: str) -> None:
    import sys

    print(line, flush=True)
    if sys.stdin.readline() == "":
        raise OptiTacError("standard input closed while waiting for the operator")


def _cmd_monitor(args: argparse.Namespace) -> int:
    from optitac_edge.bringup.monitor import command_frame, monitor_can, monitor_serial

    def say(line: str) -> None:
        print(line, flush=True)

    if args.serial is not None:
        for text in args.send:
            command_frame(text, 0)  # refuse a bad command before opening anything
        monitor_serial(args.serial, args.baud, args.duration, args.send, say, every=args.all)
    else:
        if args.send:
            raise OptiTacError("protocol v1 carries no commands on CAN: --send needs --serial")
        monitor_can(args.can, args.can_interface, args.duration, say, every=args.all)
    return 0


def _cmd_view(args: argparse.Namespace) -> int:
    from optitac_edge.cli import _cmd_run

    run_args = argparse.Namespace(**vars(args), serial=None, can=None, frames=None, fps=None, view=args.bind)
    return _cmd_run(run_args)


def _cmd_snapshot(args: argparse.Namespace) -> int:
    from types import SimpleNamespace

    from optitac_edge.core.pipeline import Pipeline
    from optitac_edge.io.files import AtomicFile
    from optitac_edge.service.bundles import obtain_bundle
    from optitac_edge.service.view.live import STAT_FIELDS, LiveView
    from optitac_edge.service.view.render import encode_png, render_published
    from optitac_edge.service.wiring import open_board_camera

    config = one_sensor_config(args)
    with open_board_camera(config) as camera:
        bundle, _ = obtain_bundle(config, camera, args.cal)
        pipeline = Pipeline(bundle)
        view = LiveView(bundle, camera.pixel_format, rate_hz=1e9)
        stats = SimpleNamespace(**dict.fromkeys(STAT_FIELDS, 0))
        try:
            taken = 0
            last = 0
            while taken < args.frames:
                captured = camera.read(config.camera.timeout_s)
                if captured is None:
                    raise OptiTacError("the camera ended before the picture was taken")
                bundle.fibers.check_frame(captured.frame, camera.pixel_format)
                est = pipeline.process(captured.frame, captured.t_ns).primary
                stats.frames += 1
                stats.contacts += int(est.contact)
                taken += int(est.baseline_ready)
                if taken >= args.frames - 1:  # the last two: the view's rate is between them
                    view.observe(captured.frame, captured.t_ns, pipeline, stats)
                    published = view.wait_published(last, timeout_s=10.0)
                    last = published.seq if published is not None else last
        finally:
            view.close()
    if published is None:
        raise OptiTacError("the view produced no picture")
    picture = render_published(published, bundle)
    with AtomicFile(args.output, "wb") as f:
        f.write(encode_png(picture))
    print(f"wrote {args.output}: {picture.shape[1]}x{picture.shape[0]} px, {len(published.contacts)} contacts")
    return 0


def _cmd_orient(args: argparse.Namespace) -> int:
    from optitac_edge.bringup.orient import orient_live
    from optitac_edge.calibration.orientation import reorient_bundle
    from optitac_edge.io.bundle_file import save_bundle
    from optitac_edge.service.bundles import obtain_bundle
    from optitac_edge.service.wiring import open_board_camera

    config = one_sensor_config(args)
    target = args.output or args.cal or config.calibration.bundle_path
    if target is None:
        raise OptiTacError(f"board {config.source} keeps no bundle (calibration.bundle is empty): "
                           "give -o CAL to write the oriented bundle")
    with open_board_camera(config) as camera:
        bundle, _ = obtain_bundle(config, camera, args.cal)
        say = _simulated_operator(camera, bundle)
        fit = orient_live(camera, bundle, args.timeout, say)
    assert fit.symmetry is not None
    evidence = f"edge presses, RMS {fit.best_rmse_mm:.1f} mm"
    bundle = reorient_bundle(bundle, fit.symmetry, evidence)
    bundle = save_bundle(bundle, target)
    what = ("confirmed" if fit.symmetry.is_identity else
            f"corrected (the fiber map was {fit.symmetry.label}; centroid, width and shape models were removed)")
    print(f"wrote {target} (id {bundle.calibration_id}): orientation {what}")
    return 0


def _simulated_operator(camera: Any, bundle: Any) -> Callable[[str], None]:
    """Show each prompt; on the simulated camera a simulated operator also does what it asks (its own
    presses ignore prompts)."""
    from optitac_edge.sim.camera import SimCamera

    if not isinstance(camera, SimCamera):
        return lambda prompt: print(prompt, flush=True)
    from optitac_edge.sim.operator import PromptFollower

    operator = PromptFollower(camera.sensor.layout.radius_mm)
    camera.press_with(operator)
    print("simulated camera: a simulated operator presses where the prompts ask", flush=True)

    def say(prompt: str) -> None:
        print(prompt, flush=True)
        operator.follow(prompt)

    return say


HANDLERS: dict[str, Callable[[argparse.Namespace], int]] = {
    "orient": _cmd_orient, "collect": _cmd_collect, "view": _cmd_view, "snapshot": _cmd_snapshot,
    "monitor": _cmd_monitor}
