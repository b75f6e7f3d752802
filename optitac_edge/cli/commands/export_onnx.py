"""``optitac-edge export-onnx``: the bundle's shape classifier as an ONNX model."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    """``export-onnx CAL -o OUT``."""
    p = sub.add_parser("export-onnx", help="export the bundle's shape classifier to ONNX")
    p.add_argument("cal", type=Path, metavar="CAL")
    p.add_argument("-o", "--output", type=Path, required=True)


def run(args: argparse.Namespace) -> int:
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


def left(args: argparse.Namespace) -> str:
    """What an interrupted run left behind, for its one line."""
    return f"{args.output} not written (unchanged)"
