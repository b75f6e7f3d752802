"""``optitac-edge sim``: a recording from the built-in simulator."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from optitac_edge.cli.common import (
    COUNT,
    SEED,
    add_board,
    add_fresh,
    add_orientation,
    add_storage,
    board_sensor,
    number,
    recording_left,
)
from optitac_edge.errors import OptiTacError

if TYPE_CHECKING:
    from optitac_edge.cli.common import Subcommands
    from optitac_edge.config import BoardConfig
    from optitac_edge.sim.optics import CameraOptics
    from optitac_edge.sim.patches import PatchPlacement


class _SimNames:
    """Names the simulator knows (``SCENARIOS`` or ``PHYSICS_NAMES``) as argparse choices, imported only when
    ``sim`` is parsed (or its help shown): every other command starts without the simulator and scipy."""

    def __init__(self, what: str) -> None:
        self._what = what

    def _names(self) -> tuple[str, ...]:
        if self._what == "physics":
            from optitac_edge.sim.physics import PHYSICS_NAMES

            return PHYSICS_NAMES
        from optitac_edge.sim.motion_scenarios import MOTION_SCENARIOS
        from optitac_edge.sim.scenarios import SCENARIOS
        from optitac_edge.sim.snapshots import SNAPSHOT_SCENARIOS

        return SCENARIOS + MOTION_SCENARIOS + SNAPSHOT_SCENARIOS

    def __contains__(self, name: object) -> bool:
        return name in self._names()

    def __iter__(self) -> Iterator[str]:
        return iter(self._names())


def add_parser(sub: Subcommands) -> None:
    """``sim OUT --scenario NAME``."""
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
    p.add_argument("--layout", type=Path, default=None, metavar="CSV",
                   help="the simulated fiber array (a layout CSV, 'optitac-edge layout' writes a hexagonal one); "
                        "default: the paper's 217 fibers at 1.5 mm. Its skin, end faces and presses scale with "
                        "its pitch")
    add_fresh(p)
    add_storage(p, None, "raw: every frame as it is (the default); fibers: the rest frames and each fiber's light "
                         "(the default of the 240 fps motion scenarios, slide, vibrate and hold: raw frames of a "
                         "slide alone are about 1 GB)")
    add_orientation(p)
    add_board(p, default=None)  # --board B --sensor ID: the sensor's patch in whole frames of its sim camera


def run(args: argparse.Namespace) -> int:
    from optitac_edge.core.layout import hex_layout
    from optitac_edge.io.layout_csv import load_layout_csv
    from optitac_edge.sim.optics import CameraOptics
    from optitac_edge.sim.physics import physics
    from optitac_edge.sim.scenarios import write_scenario

    world = physics(args.physics)
    layout = load_layout_csv(args.layout) if args.layout else None  # None: the physics' array
    n_fibers = (layout if layout is not None else hex_layout(*world.array) if world.array else hex_layout()).n_fibers
    try:
        dark = tuple(int(s) for s in args.dark_fibers.split(",") if s.strip())
    except ValueError:
        raise OptiTacError(f"--dark-fibers must be comma-separated integers, got {args.dark_fibers!r}") from None
    if any(not 0 <= i < n_fibers for i in dark) or len(set(dark)) != len(dark):
        raise OptiTacError(f"--dark-fibers must be distinct fiber indices in 0..{n_fibers - 1}")
    config = board_sensor(args)
    patch = None
    if config is None:
        optics = CameraOptics(width=args.width, height=args.height, rgb=args.rgb,
                              rotation_deg=args.rotation_deg, mirror=args.mirror, dark_fibers=dark)
    else:
        optics, patch = _simboard_sensor(args, config, dark)
    from optitac_edge.io.recording_paths import check_writable_recording

    check_writable_recording(args.out_dir, args.fresh)  # refused now, not after the simulation
    mcap = args.out_dir.suffix == ".mcap"
    out = args.out_dir.with_name(args.out_dir.name + ".dir.part") if mcap else args.out_dir
    if mcap:
        import shutil

        shutil.rmtree(out, ignore_errors=True)  # a conversion that did not finish
    if mcap and args.storage == "fibers":
        raise OptiTacError("--storage fibers: an MCAP recording holds raw frames (simulate into a directory)")
    from optitac_edge.sim.motion_scenarios import MOTION_SCENARIOS

    storage = args.storage or ("fibers" if args.scenario in MOTION_SCENARIOS and not mcap else "raw")
    path = write_scenario(out, args.scenario, seed=args.seed, frames=args.frames, optics=optics,
                          day=args.day, variant=args.variant, warmup=args.warmup, patch=patch,
                          fresh=args.fresh and not mcap, storage=storage, physics=args.physics, layout=layout)
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


def _simboard_sensor(args: argparse.Namespace, config: BoardConfig,
                     dark: tuple[int, ...]) -> tuple[CameraOptics, PatchPlacement | None]:
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


left = recording_left
