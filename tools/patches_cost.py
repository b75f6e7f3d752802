#!/usr/bin/env python3
"""Time of one camera frame holding several fiber patches: every patch's pipeline on the same frame.

    python tools/patches_cost.py [--patches 4] [--width 1280] [--height 720] [--frames 2000] [--fps 240]

Patches of 217 fibers in a grid on one camera (the simulator's ``PatchFrames``), each calibrated on its
crop and placed in the frame (``core.region.place_bundle``). One patch at a time is pressed (a 5 mm
circle), the others rest, as a hand holding an object. Prints the median and p99 per camera frame (all
patches), back to back (warm) and paced at ``--fps`` (sleeping between frames, caches cold). Issue 16's
target: 4 patches of 217 fibers on a 1280x720 camera <= 0.6 ms per frame (median).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--patches", type=int, default=4)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--fps", type=float, default=240.0)
    args = ap.parse_args()

    from optitac_edge.calibration.fibers import calibrate_fibers
    from optitac_edge.core.pipeline import Pipeline, single_threaded_opencv
    from optitac_edge.core.region import Region, place_bundle
    from optitac_edge.sim.patches import PatchFrames, crop
    from optitac_edge.sim.skin import Indenter

    cols = int(np.ceil(np.sqrt(args.patches)))
    rows = int(np.ceil(args.patches / cols))
    w, h = args.width // cols, args.height // rows
    regions = [Region((k % cols) * w, (k // cols) * h, w - 8, h - 8) for k in range(args.patches)]
    cam = PatchFrames(regions, args.width, args.height, seed=1)
    rest = np.stack([cam.frame() for _ in range(10)])
    pipes = [Pipeline(place_bundle(calibrate_fibers(crop(rest, r), "gray"), r, args.width, args.height))
             for r in regions]
    rng = np.random.default_rng(2)
    frames = []
    for i in range(120):  # distinct frames: a press on patch i % P, moving
        press = Indenter("circle", float(rng.uniform(-4, 4)), float(rng.uniform(-4, 4)), 0.0, 5.0, 3.0)
        frames.append(cam.frame([(press,) if k == i % args.patches else () for k in range(args.patches)]))
    period = 1e9 / args.fps
    out = {}
    with single_threaded_opencv():
        t = 0
        for f in rest:
            for p in pipes:
                p.process(f, t)
            t += int(period)
        for mode in ("back_to_back", "paced"):
            times = []
            next_due = time.monotonic_ns()
            for i in range(args.frames):
                f = frames[i % len(frames)]
                if mode == "paced":
                    next_due += int(period)
                    delay = next_due - time.monotonic_ns()
                    if delay > 0:
                        time.sleep(delay / 1e9)
                t0 = time.perf_counter_ns()
                for p in pipes:
                    p.process(f, t)
                times.append(time.perf_counter_ns() - t0)
                t += int(period)
            us = np.array(times[100:]) / 1e3
            out[mode] = {"median_us": round(float(np.median(us)), 1), "p99_us": round(float(np.percentile(us, 99)), 1)}
    contacts = sum(p.contacts[0].contact for p in pipes)
    print(json.dumps({"patches": args.patches, "frame": [args.width, args.height],
                      "fibers_per_patch": pipes[0].bundle.layout.n_fibers, "contacts_last_frame": int(contacts), **out}))


if __name__ == "__main__":
    main()
