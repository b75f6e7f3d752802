#!/usr/bin/env python3
"""Export recordings as a LeRobot dataset, read it back with LeRobot's loader, and compare every value with the
contacts CSV of the same recordings (``optitac-edge replay``): the check of docs/lerobot.md.

    python tools/lerobot_roundtrip.py out/seen --cal out/cal.npz --workdir /tmp/rt [--video]

Prints the values compared and how many differ (0 expected), the dataset's size and the export's time per
1 000 frames. Needs the lerobot extra (LeRobot's writer and loader). Exit status 1 when a value differs.

Compared, for every frame: the capture time (ns), the contact count, the vibration and its flag, and, in frames
with contact, the strongest contact's centroid, widths, angle, depth, force, velocity, sliding flag and id, each
as the contacts CSV writes it (its digits; an unknown value is empty there and NaN in the dataset).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from pathlib import Path

import numpy as np

from optitac_edge.cli import main as cli
from optitac_edge.core.options import MAX_CONTACTS
from optitac_edge.devtools import lerobot_features as lf

#: contacts CSV column -> digits it is written with (None: an integer)
CONTACT_COLUMNS = {"x_mm": 4, "y_mm": 4, "major_mm": 4, "minor_mm": 4, "angle_deg": 3, "depth_mm": 4, "force_n": 4,
                   "vx_mm_s": 3, "vy_mm_s": 3, "contact_id": None, "sliding": None}


def _text(value: float, digits: int | None) -> str:
    """A value as the contacts CSV writes it."""
    if digits is None:
        return str(int(value))
    return "" if not math.isfinite(value) else f"{value:.{digits}f}"


def compare(dataset: Path, contacts_csvs: list[Path], repo_id: str = "optitac/tactile") -> tuple[int, int, int]:
    """(frames, values compared, values that differ) between the dataset at ``dataset`` (read by LeRobot's
    loader, as stored) and the contacts CSVs, one per episode in order."""
    from ledataset.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(repo_id, root=dataset)
    table = ds.hf_dataset.with_format(None)  # the values as stored (float64), not float32 torch tensors
    rows = []
    for episode, path in enumerate(contacts_csvs):
        with open(path, newline="") as f:
            rows += [(episode, k, row) for k, row in enumerate(csv.DictReader(f))]
    if len(rows) != len(ds):
        return len(ds), 1, 1
    fields = {name: k for k, name in enumerate(lf.CONTACT_FIELDS)}
    compared = differ = 0
    for j, (episode, k, row) in enumerate(rows):
        got = table[j]
        state = got[lf.STATE]
        slot = np.asarray(got[lf.CONTACTS]).reshape(MAX_CONTACTS, -1)[0]
        pairs = [(row["t_ns"], str(int(got[lf.T_NS]))), (row["n_contacts"], str(int(state[0]))),
                 (row["vibration"], _text(state[1], 3)), (row["vibrating"], str(int(state[2]))),
                 (str(episode), str(int(got["episode_index"]))), (str(k), str(int(got["frame_index"])))]
        if row["contact"] == "1":
            pairs += [(row[name], _text(slot[fields[name]], digits)) for name, digits in CONTACT_COLUMNS.items()]
        else:
            pairs.append(("0", _text(slot[0], None)))
        compared += len(pairs)
        differ += sum(a != b for a, b in pairs)
    return len(rows), compared, differ


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("recording", type=Path, nargs="+")
    p.add_argument("--cal", type=Path, required=True)
    p.add_argument("--workdir", type=Path, required=True, help="where the dataset and the CSVs are written (new)")
    p.add_argument("--video", action="store_true")
    args = p.parse_args(argv)
    if args.workdir.exists():
        p.error(f"--workdir {args.workdir}: exists (give a new directory)")
    args.workdir.mkdir(parents=True)
    csvs = []
    for k, rec in enumerate(args.recording):
        csvs.append(args.workdir / f"contacts{k}.csv")
        if cli(["replay", str(rec), "--cal", str(args.cal), "-o", str(csvs[-1])]) != 0:
            return 2
    out = args.workdir / "dataset"
    t0 = time.monotonic()
    if cli(["export-lerobot", *map(str, args.recording), "--cal", str(args.cal), "-o", str(out),
            *(["--video"] if args.video else [])]) != 0:
        return 2
    seconds = time.monotonic() - t0
    frames, compared, differ = compare(out, csvs)
    size = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    print(f"roundtrip: {frames} frames, {compared} values compared, {differ} differ; dataset {size / 1e6:.2f} MB "
          f"({size / frames:.0f} bytes a frame); export {seconds:.1f} s, {seconds / frames * 1000:.2f} s per "
          "1 000 frames")
    return 0 if differ == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
