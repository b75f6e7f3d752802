"""Accuracy of every sensor of a simulated board with several sensors, against the same sensor alone.

Usage::

    python tools/board_accuracy.py [--board sim-hand] [--workdir DIR] [-o FILE.md]

For each sensor of the board (two fingertip patches on one camera and the palm
on a second camera, for ``sim-hand``) it records on day 1 the calibration set
(``rest``, ``seen``) in whole frames of the sensor's camera, where the other
patches rest, and on day 2 unseen presses (seed 5). It calibrates as
``optitac-edge calibrate fibers|centroid --board B --sensor ID`` does (the
fiber map on the region's crop, placed in the frame) and evaluates the unseen
presses as ``optitac-edge evaluate`` does. The same scenarios recorded on the
sensor alone (a camera the size of its region) give the baseline "as for one".
Cross-talk: every other sensor of the same camera processes the pressed
sensor's unseen recording, and its contact frames are counted.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from optitac_edge.calibration.evaluation import centroid_accuracy, detection
from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.calibration.measure import measure_recording
from optitac_edge.calibration.region import Region, calibrate_region
from optitac_edge.calibration.steps import calibrate_centroid
from optitac_edge.config import BoardConfig, BoardSensor, load_board_config
from optitac_edge.io.recording import Recording
from optitac_edge.sim.optics import CameraOptics
from optitac_edge.sim.patches import PatchFrames, PatchPlacement
from optitac_edge.sim.scenarios import write_scenario

CAL_DAY, EVAL_DAY, EVAL_SEED = 1, 2, 5


def _placement(config: BoardConfig, s: BoardSensor, seed: int) -> PatchPlacement | None:
    if not s.sensor.region:
        return None
    cam = config.cameras[s.sensor.camera]
    regions = config.regions_of(s.sensor.camera)
    frames = PatchFrames([Region(*r) for r in regions], cam.width, cam.height,
                         optics=CameraOptics(width=cam.width, height=cam.height), seed=seed)
    return PatchPlacement(frames, regions.index(s.sensor.region))


def record(workdir: Path, config: BoardConfig, s: BoardSensor, name: str, day: int, seed: int,
           alone: bool) -> Recording:
    """Scenario ``name`` on sensor ``s``: in its camera's whole frames, or ``alone`` at its region's size."""
    path = workdir / f"sensor{s.sensor.id}{'-alone' if alone else ''}" / f"{name}-day{day}-seed{seed}"
    if not (path / "meta.json").exists():
        cam = config.cameras[s.sensor.camera]
        placement = _placement(config, s, seed)
        if placement is None:
            write_scenario(path, name, seed=seed, day=day, optics=CameraOptics(width=cam.width, height=cam.height))
        elif alone:  # the same physical sensor (the patch's), on a camera of its region's size
            r = placement.region
            write_scenario(path, name, seed=seed, day=day, optics=CameraOptics(width=r.width, height=r.height),
                           sensor_seed=placement.frames.sensors[placement.index].sensor_seed)
        else:
            write_scenario(path, name, seed=seed, day=day, patch=placement)
    return Recording(path)


def calibrate(workdir: Path, config: BoardConfig, s: BoardSensor, alone: bool) -> Any:
    rest = record(workdir, config, s, "rest", CAL_DAY, 0, alone)
    if s.sensor.region and not alone:
        bundle = calibrate_region(rest.rest_frames(), rest.pixel_format, Region(*s.sensor.region))
    else:
        bundle = calibrate_fibers(rest.rest_frames(), rest.pixel_format)
    bundle, _ = calibrate_centroid(record(workdir, config, s, "seen", CAL_DAY, 0, alone), bundle)
    return bundle


def evaluate(rec: Recording, bundle: Any) -> dict[str, Any]:
    m = measure_recording(rec, bundle, corrected=True, progress=False)
    return {"centroid": centroid_accuracy(m, rec.truth), "detection": detection(m, rec.truth)}


def board_table(board: str, workdir: Path) -> list[str]:
    """The markdown table: one row per sensor of ``board``."""
    config = load_board_config(board, env={})
    bundles = {s.sensor.id: calibrate(workdir, config, s, alone=False) for s in config.sensors}
    header = ("| sensor | camera | region | unseen RMSE x / y, mm | alone: RMSE x / y, mm | detected | false contacts "
              "| contacts on the camera's other sensors |")
    rows = [header, "|---|---|---|---|---|---|---|---|"]
    for s in config.sensors:
        sid = s.sensor.id
        unseen = record(workdir, config, s, "unseen", EVAL_DAY, EVAL_SEED, alone=False)
        board_eval = evaluate(unseen, bundles[sid])
        alone = evaluate(record(workdir, config, s, "unseen", EVAL_DAY, EVAL_SEED, alone=True),
                         calibrate(workdir, config, s, alone=True))
        others = []
        for o in config.sensors_of(s.sensor.camera):
            if o.sensor.id != sid:
                m = measure_recording(unseen, bundles[o.sensor.id], corrected=True, progress=False)
                others.append(f"sensor {o.sensor.id}: {int(m.contact.sum())}/{len(m.contact)} frames")
        c, a, d = board_eval["centroid"], alone["centroid"], board_eval["detection"]
        region = list(s.sensor.region) if s.sensor.region else "whole frame"
        rows.append(f"| {sid} {s.sensor.name} | {s.sensor.camera} | {region} | {c.rmse_x:.3f} / {c.rmse_y:.3f} "
                    f"| {a.rmse_x:.3f} / {a.rmse_y:.3f} | {d.detected}/{d.contact_frames} | "
                    f"{d.false_contacts}/{d.rest_frames} | {'; '.join(others) or '(alone on its camera)'} |")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--board", default="sim-hand")
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/optitac-board-accuracy"))
    ap.add_argument("-o", "--output", type=Path, default=None, help="write the markdown table here")
    args = ap.parse_args()
    text = "\n".join(board_table(args.board, args.workdir)) + "\n"
    if args.output:
        args.output.write_text(text)
    else:
        print(text)


if __name__ == "__main__":
    main()
