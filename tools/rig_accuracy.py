"""The paper's experiments collected by ``optitac-edge collect`` over the simulator's virtual rig, then
calibrated and evaluated as a user would: the figures of docs/accuracy.md from rig-collected data.

Day 1 (calibration): ``seen``, ``widths``, ``shapes``; day 2 (evaluation, the sensor re-mounted on the rig
at another angle and place): ``seen``, ``unseen``, ``repeat``, ``widths``, ``shapes``; plus ``depths``.

    python tools/rig_accuracy.py [--workdir DIR] [--limit N]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import sys
import time
from pathlib import Path

from optitac_edge.cli import main

DAY1 = ("sim://?rotation=7&origin=100,80", ("seen", "widths", "shapes"))
DAY2 = ("sim://?rotation=-4&origin=98,83&surface=1.2", ("seen", "unseen", "repeat", "widths", "shapes", "depths"))


def run(*argv: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(list(argv))
    if code != 0:
        sys.exit(f"optitac-edge {' '.join(argv)}: exit {code}")
    return out.getvalue()


def main_() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--workdir", type=Path, default=Path("rig_accuracy"))
    ap.add_argument("--limit", type=int, default=None, help="presses per experiment (default: all)")
    args = ap.parse_args()
    wd = args.workdir
    wd.mkdir(parents=True, exist_ok=True)
    limit = [] if args.limit is None else ["--limit", str(args.limit)]
    t0 = time.monotonic()
    for day, (url, experiments) in (("day1", DAY1), ("day2", DAY2)):
        for k, exp in enumerate(experiments):
            rec = wd / f"{day}-{exp}"
            if not (rec / "meta.json").exists():
                seed = (100 if day == "day1" else 200) + k
                print(run("collect", exp, "--rig", url, "-o", str(rec), "--seed", str(seed), *limit).strip()
                      .splitlines()[-1])
    cal = wd / "cal.npz"
    print(run("calibrate", "fibers", str(wd / "day1-seen"), "-o", str(cal)).strip())
    print(run("calibrate", "orientation", str(wd / "day1-seen"), "--cal", str(cal)).strip())
    for step, rec in (("centroid", "seen"), ("width", "widths"), ("shapes", "shapes")):
        print(run("calibrate", step, str(wd / f"day1-{rec}"), "--cal", str(cal)).strip())
    for exp in DAY2[1]:
        if exp == "depths":
            continue
        print(run("evaluate", str(wd / f"day2-{exp}"), "--cal", str(cal)).rstrip())
    print(f"total {time.monotonic() - t0:.0f} s")


if __name__ == "__main__":
    main_()
