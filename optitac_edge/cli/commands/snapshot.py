"""``optitac-edge snapshot``: the live view's picture of a board's camera, as a PNG."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from optitac_edge.cli.common import add_board, number, one_sensor_config
from optitac_edge.errors import OptiTacError

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands


def add_parser(sub: Subcommands) -> None:
    """``snapshot -o PNG``."""
    p = sub.add_parser("snapshot", help="write the live view's picture of a board's camera to a PNG")
    add_board(p)
    p.add_argument("--cal", type=Path, default=None, metavar="CAL", help="use this bundle (default: the board's)")
    p.add_argument("-o", "--output", type=Path, required=True, metavar="PNG")
    p.add_argument("--frames", type=number(1, 10**5, integer=True), default=10,
                   help="frames processed after the baseline before the picture (default 10)")


def run(args: argparse.Namespace) -> int:

    from optitac_edge.core.frame_engine import Skip
    from optitac_edge.core.pipeline import Pipeline
    from optitac_edge.io.files import AtomicFile
    from optitac_edge.service.bundles import obtain_bundle
    from optitac_edge.service.stats import ServiceStats
    from optitac_edge.service.view.live import LiveView
    from optitac_edge.service.view.render import encode_png, render_published
    from optitac_edge.service.wiring import open_board_camera

    config = one_sensor_config(args)
    with open_board_camera(config) as camera:
        bundle, _ = obtain_bundle(config, camera, args.cal)
        pipeline = Pipeline(bundle, fps=camera.fps)
        view = LiveView(bundle, camera.pixel_format, rate_hz=1e9)
        stats = ServiceStats()
        try:
            taken = 0
            last = 0
            while taken < args.frames:
                captured = camera.read(config.camera.timeout_s)
                if captured is None:
                    raise OptiTacError("the camera ended before the picture was taken")
                result = pipeline.process(captured.frame, captured.t_ns)
                if result is Skip.BAD:  # says which frames the bundle wants
                    bundle.fibers.check_frame(captured.frame, camera.pixel_format)
                if isinstance(result, Skip):
                    stats.camera_errors += 1
                    continue
                est = result.primary
                stats.frames += 1
                stats.contacts += int(est.contact)
                taken += int(result.baseline_ready)
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
