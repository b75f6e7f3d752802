"""A public data set of a real fiber sensor, as optitac-edge recordings, and the bring-up scored on it.

Usage::

    python tools/real_dataset.py --data PATH/TO/RGB_sensor -o out/realdata [--baseline 3]

The data set (github.com/baimukashev/RGB_sensor: D. Baimukashev, Z. Kappassov, H. A. Varol, "Shear,
Torsion and Pressure Tactile Sensor via Plastic Optofiber Guided Imaging", RA-L 2020) holds PNG snapshots
of a 61-fiber, ~4 mm-pitch colour-coded sensor seen by a 640 x 480 webcam, pressed by a UR10 with a 6-axis
force/torque sensor on five days; labels give each normal press's position (radius and angle of the
robot's pose about the sensor's centre) and force. This tool reads only the labelled normal presses (its
public label files; nothing of it is copied here) and writes one recording a day:

* a frame is *rest* below 0.35 N, a *contact* from 1 N (the acceptance's presses), and unscored between;
* every scored frame is preceded by a tare over the ``--baseline`` rest frames of its day nearest to it in
  time (itself never: a rest frame is scored against other rest frames), as a user of snapshots would take
  the baseline from the rest frames around each press;
* the truth: the robot's x, y (mm; the layout's orientation is settled from the presses by ``calibrate
  orientation``), a 10 mm circle (the indenter's size is not in the labels), depth from the robot's z where
  the labels have it (else 1 mm), the force (N).

Then, leaving one day out at a time, it calibrates the days left (``calibrate fibers`` on the first day's
rest frames, ``levels``, ``orientation``, ``centroid``, ``depth``: the force model is chosen on the load
cell's forces alone) and scores the day left out: detection of contact frames, false contacts on rest
frames, location (RMS, mm and pitches, against predicting the scored presses' mean position), force (RMS,
against predicting the calibration days' mean force), printed per day and pooled.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from optitac_edge.calibration.evaluation import centroid_accuracy, detected_rows, detection
from optitac_edge.calibration.measure import measure_sessions
from optitac_edge.cli import main as cli
from optitac_edge.io.bundle_file import load_bundle
from optitac_edge.io.recording import Recording, RecordingMeta
from optitac_edge.io.recording_writer import RecordingWriter

REST_N, CONTACT_N = 0.35, 1.0
#: The labelled sessions by day (test name prefix -> day).
DAYS = {"Normal_Test1": "nov21", "Normal_Test2": "nov21", "Normal_TEST3": "nov23", "Normal_TestBandwidth": "nov28",
        "Normal_Test_BandwidthHiger": "nov30"}
FPS = 20.0  # the data set's camera: frame k of a test at k / 20 s


@dataclass(frozen=True)
class Press:
    """A truth row's press (what RecordingWriter.write_truth reads)."""

    x_mm: float
    y_mm: float
    depth_mm: float
    shape: str = "circle"
    angle_deg: float = math.nan
    size_mm: float = 10.0


@dataclass(frozen=True)
class Label:
    name: str
    day: str
    t_s: float
    x_mm: float
    y_mm: float
    force_n: float
    z_m: float


def _day(name: str) -> str | None:
    return next((day for prefix, day in DAYS.items() if name.startswith(prefix)), None)


def read_labels(data: Path) -> list[Label]:
    """The labelled normal presses whose image is in the data set."""
    images = data / "data" / "images"
    out: dict[str, Label] = {}
    for path in sorted((data / "data" / "labels" / "testing").rglob("*.csv")):
        for r in csv.reader(path.open()):
            if len(r) < 13 or not r[0].endswith(".png") or not (images / r[0]).exists() or r[4] != "1":
                continue
            name, day = r[0][:-4], _day(r[0])
            if day is None:
                continue
            k = int(name.rsplit("_", 1)[1])
            rad, ang = float(r[6]), math.radians(float(r[9]))
            out[name] = Label(name, day, k / FPS, 1000 * rad * math.cos(ang), 1000 * rad * math.sin(ang),
                              -float(r[12]), float(r[8]))
    valid = data / "data" / "labels" / "reshaped_validABC.csv"
    if valid.exists():
        for r in csv.reader(valid.open()):
            if len(r) < 5 or r[1] != "1.0" or not (images / r[0]).exists() or r[0][:-4] in out:
                continue
            name, day = r[0][:-4], _day(r[0])
            if day is not None:
                k = int(name.rsplit("_", 1)[1])
                out[name] = Label(name, day, k / FPS, float(r[2]), float(r[3]), -float(r[4]), math.nan)
    return sorted(out.values(), key=lambda label: (label.name.rsplit("_", 1)[0], label.t_s))


def _frame(data: Path, name: str) -> np.ndarray | None:
    image = cv2.imread(str(data / "data" / "images" / f"{name}.png"), cv2.IMREAD_COLOR)
    return None if image is None else np.ascontiguousarray(image[:, :, ::-1])


def write_day(data: Path, out: Path, labels: list[Label], baseline: int) -> tuple[int, int] | None:
    """One day's recording (see the module docstring); (rest, contact) frames scored, None with too few."""
    frames = {lab.name: _frame(data, lab.name) for lab in labels}
    labels = [lab for lab in labels if frames[lab.name] is not None]
    rest = [lab for lab in labels if abs(lab.force_n) < REST_N]
    scored = [lab for lab in labels if abs(lab.force_n) < REST_N or lab.force_n >= CONTACT_N]
    if len(rest) < 2:
        return None
    z_touch = max((lab.z_m for lab in rest if math.isfinite(lab.z_m)), default=math.nan)
    plan: list[tuple[Label, bool]] = [(rest[k % len(rest)], False) for k in range(5)]
    tares = []
    for lab in scored:
        others = sorted((r for r in rest if r.name != lab.name), key=lambda r: abs(r.t_s - lab.t_s))[:baseline]
        tares.append({"frame": len(plan), "frames": len(others)})
        plan += [(r, False) for r in others] + [(lab, True)]
    meta = RecordingMeta(rest_frames=5, fps=1.0, extra={"tares": tares, "source": "baimukashev/RGB_sensor"})
    with RecordingWriter(out, len(plan), (480, 640, 3), meta, with_truth=True, force_column=True,
                         replace=True) as w:
        for k, (lab, score) in enumerate(plan):
            w.write(k, frames[lab.name], round(k * 60e9))  # a minute apart: independent snapshots
            if score and abs(lab.force_n) < REST_N:
                w.write_truth(k, None, force_n=max(lab.force_n, 0.0))
            elif score:
                depth = 1000 * (z_touch - lab.z_m) if math.isfinite(lab.z_m + z_touch) else 1.0
                w.write_truth(k, Press(lab.x_mm, lab.y_mm, max(depth, 0.0)), force_n=lab.force_n)
    return sum(abs(lab.force_n) < REST_N for lab in scored), sum(lab.force_n >= CONTACT_N for lab in scored)


def quiet(args: list[str]) -> str:
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        status = cli(args)
    if status:
        raise SystemExit(f"optitac-edge {' '.join(args)}: exit {status}\n{text.getvalue()}")
    return text.getvalue().strip()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, required=True, help="a checkout of the data set")
    ap.add_argument("-o", "--output", type=Path, default=Path("out/realdata"))
    ap.add_argument("--baseline", type=int, default=3, help="rest frames each scored frame's baseline is from")
    a = ap.parse_args()
    a.output.mkdir(parents=True, exist_ok=True)
    by_day: dict[str, list[Label]] = {}
    for lab in read_labels(a.data):
        by_day.setdefault(lab.day, []).append(lab)
    days = {}
    for day, labels in sorted(by_day.items()):
        counts = write_day(a.data, a.output / day, labels, a.baseline)
        print(f"{day}: {'too few rest frames' if counts is None else f'{counts[0]} rest, {counts[1]} contact frames'}")
        if counts is not None:
            days[day] = a.output / day
    layout = a.output / "hex61.csv"
    quiet(["layout", "--rings", "4", "--pitch-mm", "4", "-o", str(layout)])
    pooled: dict[str, list] = {"found": [], "false": [], "err": [], "truth": [], "force": [], "mean_force": []}
    for left, held_out in days.items():
        cal = a.output / f"cal-without-{left}.npz"
        train = [str(p) for d, p in days.items() if d != left]
        quiet(["calibrate", "fibers", train[0], "-o", str(cal), "--layout", str(layout)])
        for step in ("levels", "orientation", "centroid", "depth"):
            try:
                print(f"  without {left}: {quiet(['calibrate', step, *train, '--cal', str(cal)])[:160]}")
            except SystemExit as exc:
                print(f"  without {left}: calibrate {step} refused: {str(exc).splitlines()[-1][:160]}")
        bundle = load_bundle(cal)
        m, truth = measure_sessions([Recording(held_out)], bundle)
        d, c = detection(m, truth), centroid_accuracy(m, truth)
        rows = np.flatnonzero(detected_rows(m, truth))
        err = np.stack([m.x_mm[truth.frame[rows]] - truth.x_mm[rows], m.y_mm[truth.frame[rows]] - truth.y_mm[rows]], 1)
        pooled["found"] += [d.detected, d.contact_frames]
        pooled["false"] += [d.false_contacts, d.rest_frames]
        pooled["err"].append(err)
        pooled["truth"].append(np.stack([truth.x_mm[truth.contact], truth.y_mm[truth.contact]], 1))
        seen = [Recording(days[d]).truth for d in days if d != left]
        mean_force = float(np.mean(np.concatenate([t.force_n[t.contact] for t in seen if t.force_n is not None])))
        assert truth.force_n is not None
        pooled["force"].append(m.force_n[truth.frame[rows]] - truth.force_n[rows])
        pooled["mean_force"].append(mean_force - truth.force_n[truth.contact])
        print(f"{left} held out: detection {d.detected}/{d.contact_frames}, false contacts {d.false_contacts}/"
              f"{d.rest_frames}, location RMSE {math.hypot(c.rmse_x, c.rmse_y):.2f} mm")
    found = sum(pooled["found"][0::2]), sum(pooled["found"][1::2])
    false = sum(pooled["false"][0::2]), sum(pooled["false"][1::2])
    err, truth_xy = np.concatenate(pooled["err"]), np.concatenate(pooled["truth"])
    rmse = float(np.sqrt(np.mean(np.sum(err ** 2, axis=1))))
    mean = float(np.sqrt(np.mean(np.sum((truth_xy - truth_xy.mean(axis=0)) ** 2, axis=1))))
    force = np.concatenate(pooled["force"])
    force_rmse = float(np.sqrt(np.mean(force[np.isfinite(force)] ** 2))) if np.isfinite(force).any() else math.nan
    mean_force = float(np.sqrt(np.mean(np.concatenate(pooled["mean_force"]) ** 2)))
    figures = {"detection": found, "false_contacts": false, "location_rmse_mm": round(rmse, 2),
               "location_rmse_pitch": round(rmse / 4.0, 3), "mean_predictor_mm": round(mean, 2),
               "force_rmse_n": round(force_rmse, 2), "mean_force_predictor_n": round(mean_force, 2)}
    print("pooled over the days left out:", json.dumps(figures))
    return 0


if __name__ == "__main__":
    sys.exit(main())
