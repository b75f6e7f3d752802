"""``optitac-edge orient``: the layout's orientation from two presses, written into the bundle."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from optitac_edge.cli.common import add_board, number, one_sensor_config
from optitac_edge.errors import OptiTacError

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands
    from optitac_edge.core.bundle import CalibrationBundle
    from optitac_edge.io.cameras.base import Camera


def add_parser(sub: Subcommands) -> None:
    """``orient``."""
    p = sub.add_parser("orient", help="find the layout's orientation from two presses (+x edge, then +y edge) "
                                      "and write it into the bundle")
    add_board(p)
    p.add_argument("--cal", type=Path, default=None, metavar="CAL",
                   help="bundle to check and correct (default: the board's)")
    p.add_argument("-o", "--output", type=Path, default=None, metavar="CAL",
                   help="write the oriented bundle here (default: where it was read from)")
    p.add_argument("--timeout", type=number(1, 3600), default=120.0, metavar="S",
                   help="give up after S seconds of camera time (default 120)")


def run(args: argparse.Namespace) -> int:
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


def _simulated_operator(camera: Camera, bundle: CalibrationBundle) -> Callable[[str], None]:
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


def left(args: argparse.Namespace) -> str:
    """What an interrupted run left behind, for its one line."""
    return "bundle unchanged"
