"""The bring-up guide (docs/bring-up.md) end to end on the simulator, for a hexagonal array of any size.

Usage::

    python tools/bringup_check.py --rings 4 --pitch-mm 4 [--workdir out/bringup61] [--limit N]
    python tools/bringup_check.py --rings 18 --pitch-mm 1.5 --workdir out/bringup1027

Every step is the command line a user runs: ``layout`` writes the array's CSV, a board config names it for
the simulated camera and for calibration, ``collect`` drives the virtual rig (``sim://``) through the
``seen``, ``unseen``, ``widths`` and ``depths`` experiments (the first collection calibrates the fiber map
from the camera's rest frames), then ``calibrate levels``, ``orientation``, ``centroid``, ``width`` and
``depth``, and ``evaluate --strict`` on the unseen presses. It prints each step's line and a summary in
pitches; the exit status is ``evaluate --strict``'s.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import re
import sys
import time
from pathlib import Path

from optitac_edge.cli import main as cli

BOARD = """config_version = 1
description = "a simulated {n}-fiber array at {pitch} mm"
[sensor]
id = 0
name = "sim{n}"
[camera]
backend = "sim"
width = 640
height = 480
fps = 60
pixel_format = "gray"
warmup_frames = 0
[camera.options]
layout = "{layout}"
[calibration]
bundle = "{bundle}"
layout = "{layout}"
rest_frames = 10
[link]
transport = "none"
[led]
enabled = false
"""


def run(args: list[str]) -> tuple[int, str]:
    """One command line, its exit status and what it printed."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = cli(args)
    text = out.getvalue()
    print(f"$ optitac-edge {' '.join(args)}\n{text}", end="", flush=True)
    return status, text


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rings", type=int, required=True)
    ap.add_argument("--pitch-mm", type=float, required=True)
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--limit", type=int, default=None, help="presses of seen, unseen, widths, depths each")
    a = ap.parse_args()
    work = (a.workdir or Path(f"out/bringup-{a.rings}-{a.pitch_mm:g}")).resolve()
    work.mkdir(parents=True, exist_ok=True)
    layout, bundle, board = work / "layout.csv", work / "cal.npz", work / "board.toml"
    t0 = time.time()
    run(["layout", "--rings", str(a.rings), "--pitch-mm", str(a.pitch_mm), "-o", str(layout)])
    n = 3 * a.rings * (a.rings + 1) + 1
    board.write_text(BOARD.format(n=n, pitch=a.pitch_mm, layout=layout, bundle=bundle))
    limit = [] if a.limit is None else ["--limit", str(a.limit)]
    for experiment in ("seen", "unseen", "widths", "depths"):
        run(["collect", experiment, "--rig", "sim://", "--board", str(board), "-o", str(work / experiment),
             "--fresh", *limit])
    seen = str(work / "seen")
    for step, rec in (("levels", seen), ("orientation", seen), ("centroid", seen),
                      ("width", str(work / "widths")), ("depth", str(work / "depths"))):
        status, _ = run(["calibrate", step, rec, "--cal", str(bundle)])
        if status:
            return status
    status, text = run(["evaluate", str(work / "unseen"), "--cal", str(bundle), "--strict"])
    rmse = re.search(r"centroid \(\d+ frames\): RMSE x ([\d.]+) mm, y ([\d.]+) mm", text)
    if rmse:
        x, y = (float(v) for v in rmse.groups())
        print(f"summary: {n} fibers at {a.pitch_mm:g} mm; unseen centroid RMSE {x / a.pitch_mm:.3f} / "
              f"{y / a.pitch_mm:.3f} pitch; {(time.time() - t0) / 60:.1f} min")
    return status


if __name__ == "__main__":
    sys.exit(main())
