"""The real-statistics physics end to end: calibrated on one day's snapshot sessions, scored on another's.

Usage::

    python tools/real_table.py [--workdir out/real] [--sessions 2] [--days 1,2]

The ``real`` physics (:mod:`optitac_edge.sim.real`: a 61-fiber 4 mm array whose fibers wander, days that
change each fiber's light by up to 30 %, colour-coded fibers, stray light) recorded as the real data set was:
hour-long sessions of snapshots 20 s apart (``sim --scenario snapshots``), the baseline taken again every 5
minutes. Day 1's sessions calibrate the bundle with the command lines of the bring-up guide (``calibrate
fibers``, ``levels``, ``orientation``, ``centroid``, ``depth``); day 2's sessions are scored: detection of
contact frames, false contacts on rest frames (minutes to an hour from each session's start, hours from the
calibration), location in pitches, depth and force against their floors (each model's own held-out error at
calibration: the sensor's repeatability within a day). The same data through the levels of the rest
frames' noise alone (no ``calibrate levels``) is the row before.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from optitac_edge.calibration.evaluation import centroid_accuracy, depth_accuracy, detection
from optitac_edge.calibration.measure import measure_sessions
from optitac_edge.cli import main as cli
from optitac_edge.io.bundle_file import load_bundle
from optitac_edge.io.recording import Recording
from optitac_edge.sim.scenarios import write_scenario


def quiet(args: list[str]) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = cli(args)
    if status:
        raise SystemExit(f"optitac-edge {' '.join(args)} exited {status}:\n{out.getvalue()}")
    return out.getvalue()


def score(bundle_path: Path, recs: list[Recording]) -> dict[str, float]:
    bundle = load_bundle(bundle_path)
    m, truth = measure_sessions(recs, bundle)
    d, c = detection(m, truth), centroid_accuracy(m, truth)
    pitch = bundle.layout.pitch_mm
    out = {"detection": d.detected / d.contact_frames, "false": d.false_contacts / d.rest_frames,
           "contact_frames": d.contact_frames, "rest_frames": d.rest_frames,
           "location_pitch": math.hypot(c.rmse_x, c.rmse_y) / pitch if c.n else math.nan,
           "location_x_pitch": c.rmse_x / pitch, "location_y_pitch": c.rmse_y / pitch}
    dr = depth_accuracy(m, truth)
    if dr is not None:
        out.update(depth_rmse_mm=dr.depth_rmse_mm, force_rmse_n=dr.force_rmse_n)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--workdir", type=Path, default=Path("out/real"))
    ap.add_argument("--sessions", type=int, default=2, help="snapshot sessions a day")
    ap.add_argument("--days", default="1,2", help="the calibration day and the scored day")
    ap.add_argument("--json", type=Path, default=None, help="write the figures here too")
    a = ap.parse_args()
    cal_day, eval_day = (int(v) for v in a.days.split(","))
    work = a.workdir
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    days: dict[int, list[Path]] = {}
    for day in (cal_day, eval_day):
        days[day] = [write_scenario(work / f"day{day}-{k}", "snapshots", seed=100 * day + k, day=day, physics="real",
                                    fresh=True) for k in range(a.sessions)]
    layout = work / "hex61.csv"
    quiet(["layout", "--rings", "4", "--pitch-mm", "4", "-o", str(layout)])
    cal, before = work / "cal.npz", work / "cal-noise-levels.npz"
    recs = [str(p) for p in days[cal_day]]
    print(quiet(["calibrate", "fibers", recs[0], "-o", str(cal), "--layout", str(layout)]).strip())
    shutil.copy(cal, before)
    lines = {}
    for step in ("levels", "orientation", "centroid", "depth"):
        lines[step] = quiet(["calibrate", step, *recs, "--cal", str(cal)]).strip()
        print(lines[step])
    for step in ("orientation", "centroid", "depth"):  # the same steps on the rest frames' noise alone
        with contextlib.suppress(SystemExit):
            quiet(["calibrate", step, *recs, "--cal", str(before)])
    scored = [Recording(p) for p in days[eval_day]]
    after, old = score(cal, scored), score(before, scored)
    meta = load_bundle(cal).extra_meta
    floors = {"depth_mm": meta["depth_fit"]["heldout_depth_rmse_mm"],
              "force_n": meta["depth_fit"].get("heldout_force_rmse_n", math.nan)}
    figures = {"after": after, "before": old, "floors": floors, "levels": meta["levels"],
               "minutes": round((time.time() - t0) / 60, 1)}
    print(json.dumps(figures, indent=1, default=float))
    if a.json:
        a.json.write_text(json.dumps(figures, indent=1, default=float))
    ok = (after["detection"] >= 0.95 and after["false"] <= 0.02 and after["location_pitch"] <= 0.25
          and after["depth_rmse_mm"] <= 1.5 * floors["depth_mm"] and after["force_rmse_n"] <= 1.5 * floors["force_n"])
    print(f"targets (detection >= 95 %, false <= 2 %, location <= 0.25 pitch, depth and force <= 1.5 x floor): "
          f"{'met' if ok else 'NOT met'}")
    return 0 if ok else 1


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    sys.exit(main())
