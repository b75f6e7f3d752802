"""Fiber-map acceptance sweep on simulated rest frames; prints one line per case and a summary.

Usage: python tools/fibermap_sweep.py [--step-deg 15] [--sizes 640x480,1280x720,1920x1080]

A case passes when every live fiber is assigned to the blob nearest its true
centre (within 0.3 pitch), no blob is left unmatched, and the dead set equals
the simulator's dark fibers exactly.
"""

from __future__ import annotations

import argparse
import itertools
import time

import numpy as np

from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.core.layout import hex_layout
from optitac_edge.errors import FiberMapError
from optitac_edge.sim.optics import CameraOptics
from optitac_edge.sim.sensor import SimulatedSensor

DARK = (0, 37, 108, 150, 216)


def run_case(width: int, height: int, rotation: float, mirror: bool, hint_error: float,
             dark: tuple[int, ...], seed: int) -> tuple[bool, str]:
    layout = hex_layout()
    sensor = SimulatedSensor(optics=CameraOptics(width=width, height=height, rotation_deg=rotation,
                                                 mirror=mirror, dark_fibers=dark), seed=seed)
    frames = [sensor.frame() for _ in range(5)]
    t0 = time.perf_counter()
    try:
        bundle = calibrate_fibers(frames, "gray", rotation_hint_deg=rotation + hint_error, mirror=mirror)
    except FiberMapError as exc:
        return False, f"refused: {exc}"
    dt = time.perf_counter() - t0
    table = bundle.fibers
    pitch_px = bundle.transform.scale_px_per_mm * layout.pitch_mm
    err = np.linalg.norm(table.centroid_px - sensor.fiber_centres_px, axis=1)
    live = ~table.dead
    dead = tuple(int(i) for i in np.flatnonzero(table.dead))
    ok = (dead == tuple(sorted(dark)) and len(table.unmatched_px) == 0
          and bool(np.all(err[live] < 0.3 * pitch_px)))
    return ok, (f"found {int(live.sum())}/217 dead={list(dead)} unmatched={len(table.unmatched_px)} "
                f"max err {err[live].max() / pitch_px:.3f} pitch, {dt * 1000:.0f} ms")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--step-deg", type=float, default=15.0)
    ap.add_argument("--sizes", default="640x480,1280x720,1920x1080")
    args = ap.parse_args()
    total = passed = 0
    for size in args.sizes.split(","):
        w, h = (int(v) for v in size.split("x"))
        step = args.step_deg if w <= 640 else args.step_deg * 3
        for rot, mirror, hint, dark in itertools.product(np.arange(0, 360, step), (False, True),
                                                        (-20.0, 20.0), ((), DARK)):
            ok, msg = run_case(w, h, float(rot), mirror, hint, dark, seed=total)
            total += 1
            passed += ok
            print(f"{'PASS' if ok else 'FAIL'} {w}x{h} rot {rot:5.1f} mirror {mirror!s:5} hint {hint:+.0f} "
                  f"dark {len(dark)}: {msg}", flush=True)
    print(f"{passed} passed, {total - passed} failed")


if __name__ == "__main__":
    main()
