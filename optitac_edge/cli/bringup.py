"""Bring-up commands: ``orient`` (and, as they come, ``collect``, ``monitor``, ``view``, ``snapshot``)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import Any

from optitac_edge.cli.common import add_board, board_config, number
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


def _cmd_orient(args: argparse.Namespace) -> int:
    from optitac_edge.bringup.orient import orient_live
    from optitac_edge.calibration.orientation import mark_verified, reorient_bundle
    from optitac_edge.io.bundle_file import save_bundle
    from optitac_edge.service.wiring import obtain_bundle, open_board_camera

    config = board_config(args)
    target = args.output or args.cal or config.calibration.bundle_path
    if target is None:
        raise OptiTacError(f"board {config.source} keeps no bundle (calibration.bundle is empty): "
                           "give -o CAL to write the oriented bundle")
    with open_board_camera(config) as camera:
        bundle, _ = obtain_bundle(config, camera, args.cal)
        fit = orient_live(camera, bundle, args.timeout, lambda prompt: print(prompt, flush=True))
    assert fit.symmetry is not None
    evidence = f"edge presses, RMS {fit.best_rmse_mm:.1f} mm"
    bundle = (mark_verified(bundle, evidence) if fit.symmetry.is_identity
              else reorient_bundle(bundle, fit.symmetry, evidence))
    bundle = save_bundle(bundle, target)
    what = ("confirmed" if fit.symmetry.is_identity else
            f"corrected (the fiber map was {fit.symmetry.label}; centroid, width and shape models were removed)")
    print(f"wrote {target} (id {bundle.calibration_id}): orientation {what}")
    return 0


HANDLERS: dict[str, Callable[[argparse.Namespace], int]] = {"orient": _cmd_orient}
