"""Contact motion and vibration on simulated sensors under every simulated physics: the table of docs/motion.md.

Usage::

    python tools/motion_table.py [-o docs/motion.md] [--workdir DIR] [--physics all] [--hold-s 120]
                                 [--default-hold-s 600]

For every physics (:mod:`optitac_edge.sim.physics`) the default sensor is calibrated as the accuracy
table does (``tools/accuracy_table.py``: rest, seen and widths recorded on day 1; the fiber map, the
noise levels, the centroid map and the width model), then the motion scenarios are recorded on day 2
(another day's drift: camera shift, LED and pin gain, depth jitter) and measured with ``optitac-edge
evaluate``'s motion metrics (:mod:`optitac_edge.calibration.motion_report`): ``slide`` and ``vibrate``
(:mod:`optitac_edge.sim.motion_scenarios`) and ``hold`` (static presses breathing in depth, LEDs warming
up, fibers drifting), ``--hold-s`` seconds of it (``--default-hold-s`` under the default physics). The
same code and constants everywhere; nothing is tuned per physics.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import time
from pathlib import Path

from accuracy_table import CAL_DAY, EVAL_DAY, configs, measured_noise, record  # tools/: run from the project

from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.calibration.measure import measure_recording
from optitac_edge.calibration.motion_report import MotionReport, motion_report
from optitac_edge.calibration.steps import calibrate_centroid, calibrate_width
from optitac_edge.io.recording import Recording
from optitac_edge.sim.motion_scenarios import MOTION_FPS
from optitac_edge.sim.physics import PHYSICS_NAMES
from optitac_edge.sim.scenarios import write_scenario

TARGETS = {"velocity RMSE, steady (mm/s)": "≤ 3", "onset at ≥ 10 mm/s (frames of sliding)": "≤ 3",
           "ids per press (30 mm slide)": "1", "false slips": "0", "vibration found after (frames)": "≤ 5",
           "false vibration events": "0"}


def bundle_for(workdir: Path, physics: str):  # type: ignore[no-untyped-def]
    cal = {n: record(workdir, 0, CAL_DAY, n, seed=100 + k, physics=physics)
           for k, n in enumerate(("rest", "seen", "widths"))}
    rest = cal["rest"]
    bundle = calibrate_fibers(rest.rest_frames(), rest.pixel_format, rotation_hint_deg=0.0, mirror=False)
    measured = measured_noise(bundle)
    bundle = bundle.with_updates(options=dataclasses.replace(configs(measured)["all (default)"].options, **measured))
    bundle, _ = calibrate_centroid(cal["seen"], bundle, fill="auto")
    bundle, _ = calibrate_width(cal["widths"], bundle, kind="auto")
    return bundle


def motion_rec(workdir: Path, physics: str, name: str, frames: int | None) -> Recording:
    path = workdir / f"motion-{physics}" / f"{name}-{frames or 'all'}"
    if not (path / "meta.json").exists():
        write_scenario(path, name, seed=300, day=EVAL_DAY, physics=physics, frames=frames, storage="fibers")
    return Recording(path)


def rows(slide: MotionReport, shake: MotionReport, hold: MotionReport) -> dict[str, str]:
    fast = [f for s, f in slide.onsets if s >= 10.0]
    slips = slide.false_slips + shake.false_slips + hold.false_slips
    held = slide.held_s + shake.held_s + hold.held_s
    quiet = slide.quiet_s + shake.quiet_s + hold.quiet_s
    found = list(shake.shakes)
    return {
        "velocity RMSE, steady (mm/s)": f"{slide.velocity_rmse_mm_s:.2f}",
        "worst speed's RMSE (mm/s)": max(f"{v:.2f} at {s:g}" for s, (_, v) in slide.velocity_rmse_by_speed.items()),
        "onset at ≥ 10 mm/s (frames of sliding)": ("-" if None in fast else f"max {max(fast)}") + f" of {len(fast)}",
        "onset at 2 / 5 mm/s (frames)": " / ".join("-" if f is None else str(f) for s, f in slide.onsets if s < 10),
        "ids per press (30 mm slide)": str(max(slide.ids_per_press)),
        "false slips": f"{slips} in {held / 60:.1f} min",
        "vibration found after (frames)": ("-" if None in found else f"max {max(found)}") + f" of {len(found)}",
        "false vibration events": f"{slide.false_vibrations + shake.false_vibrations + hold.false_vibrations} in "
                                  f"{quiet / 60:.1f} min",
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("-o", "--out", type=Path, default=Path("docs/motion.md"))
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/optitac-motion"))
    ap.add_argument("--physics", default="all")
    ap.add_argument("--hold-s", type=float, default=120.0)
    ap.add_argument("--default-hold-s", type=float, default=600.0)
    args = ap.parse_args()
    names = list(PHYSICS_NAMES) if args.physics == "all" else args.physics.split(",")
    t0 = time.monotonic()
    table: dict[str, dict[str, str]] = {}
    for name in names:
        print(f"physics {name} ...", flush=True)
        bundle = bundle_for(args.workdir, name)
        hold_s = args.default_hold_s if name == "default" else args.hold_s
        reports = []
        for scenario, frames in (("slide", None), ("vibrate", None), ("hold", round(hold_s * MOTION_FPS))):
            rec = motion_rec(args.workdir, name, scenario, frames)
            r = motion_report(measure_recording(rec, bundle, progress=False), rec.truth, rec.meta.fps)
            assert r is not None
            reports.append(r)
        table[name] = rows(*reports)
    keys = list(next(iter(table.values())))
    lines = ["| metric | target | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    lines += [f"| {k} | {TARGETS.get(k, '–')} | " + " | ".join(table[n][k] for n in names) + " |" for k in keys]
    minutes = (time.monotonic() - t0) / 60
    made = f"Made by `python tools/motion_table.py` in {minutes:.1f} min on {platform.machine()}"
    lines += ["", f"{made} (Python {platform.python_version()})."]
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
