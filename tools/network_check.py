"""A subscriber in another process gets every contact of a run on Zenoh, equal to the contacts CSV of
the same frames, and how late.

Usage::

    python tools/network_check.py [--seconds 60] [--fps 240] [--workdir DIR]

It simulates the ``unseen`` presses (448 frames, 9 presses) and a fiber map from
the ``rest`` recording, restamps the presses at ``--fps`` and makes them a camera
that loops (``[camera.options] loop = true``), paced at ``--fps``. A subscriber
(``examples/zenoh_subscriber.py``: plain Zenoh, CDR decoded by rosbags with the
shipped ``.msg`` files) listens on loopback; ``optitac-edge run --publish zenoh:CFG``
runs for ``--seconds``. The contacts CSV of the same frames comes from the offline
path: the run's frames, in order, with the same timestamps, through a
:class:`~optitac_edge.core.pipeline.Pipeline` of the same bundle, written by
:class:`~optitac_edge.io.contacts_csv.ContactsCsvWriter` (what ``replay`` writes).

Printed: frames processed, messages received (missing, out of order), frames whose
contacts differ from the CSV (every contact count, the strongest contact's values
at the CSV's digits, its id and shape), and the latency from the frame's capture
(its CLOCK_MONOTONIC timestamp) to the subscriber's callback: p50, p99, max.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.io.bundle_file import load_bundle, save_bundle
from optitac_edge.io.contacts_csv import ContactsCsvWriter
from optitac_edge.io.recording import Recording
from optitac_edge.sim.scenarios import write_scenario

ROOT = Path(__file__).resolve().parent.parent
SUBSCRIBER = ROOT / "examples" / "zenoh_subscriber.py"
DIGITS = (("x_mm", 4), ("y_mm", 4), ("major_mm", 4), ("minor_mm", 4), ("angle_deg", 3), ("strength", 3),
          ("depth_mm", 4), ("force_n", 4))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def prepare(work: Path, fps: float) -> tuple[Path, Path]:
    """(the presses restamped at ``fps``, the bundle)."""
    presses = write_scenario(work / "unseen", "unseen", seed=1, fresh=True)
    rest = Recording(write_scenario(work / "rest", "rest", seed=2, fresh=True))
    bundle = work / "cal.npz"
    save_bundle(calibrate_fibers(rest.rest_frames(), rest.pixel_format), bundle)
    n = len(Recording(presses))
    np.save(presses / "timestamps.npy", np.round(np.arange(n) * 1e9 / fps).astype(np.int64))
    meta = json.loads((presses / "meta.json").read_text())
    meta["fps"] = fps
    (presses / "meta.json").write_text(json.dumps(meta, indent=2))
    return presses, bundle


def expected_csv(presses: Path, bundle: Path, n_frames: int, out: Path) -> list[dict[str, str]]:
    """The contacts CSV of the run's frames: the recording looped, with the camera's timestamps."""
    rec = Recording(presses)
    times = rec.t_ns - rec.t_ns[0]
    period = int(1e9 / rec.meta.fps)
    pipeline = Pipeline(load_bundle(bundle))
    with ContactsCsvWriter(out) as writer:
        shift = 0
        for k in range(n_frames):
            i = k % len(rec)
            if k and i == 0:
                shift += int(times[-1]) + period
            t = shift + int(times[i])
            writer.write(k, pipeline.process_recorded(rec.frames[i], t))
    return list(csv.DictReader(out.open()))


def differs(message: dict, row: dict[str, str]) -> str | None:
    """Why a Contacts message is not the CSV row of its frame (None: it is)."""
    contacts = message["contacts"]
    want = int(row["n_contacts"]) if row["contact"] == "1" else 0
    if len(contacts) != want:
        return f"{len(contacts)} contacts, the CSV {want}"
    if not contacts:
        return None
    c = contacts[0]
    for key, digits in DIGITS:
        shown = "" if c[key] is None else f"{c[key]:.{digits}f}"
        if shown != row[key]:
            return f"{key} {shown}, the CSV {row[key]}"
    if c["id"] != int(row["contact_id"]) or c["shape"] != row["shape"]:
        return f"id/shape {c['id']}/{c['shape']!r}, the CSV {row['contact_id']}/{row['shape']!r}"
    return None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--fps", type=float, default=240.0)
    p.add_argument("--workdir", type=Path, default=None)
    args = p.parse_args(argv)
    work = args.workdir or Path(tempfile.mkdtemp(prefix="optitac-network-"))
    work.mkdir(parents=True, exist_ok=True)
    presses, bundle = prepare(work, args.fps)
    port = _free_port()
    zenoh_cfg = work / "zenoh.json5"
    zenoh_cfg.write_text(f'{{ mode: "peer", connect: {{ endpoints: ["tcp/127.0.0.1:{port}"] }}, '
                         'scouting: { multicast: { enabled: false } } }')
    board = work / "board.toml"
    board.write_text(f'[sensor]\nname = "thumb"\n[camera]\nbackend = "recording"\nrecording = "{presses}"\n'
                     f'[camera.options]\nloop = true\n[calibration]\nbundle = "{bundle}"\n'
                     f'[publish.zenoh]\nconfig = "{zenoh_cfg}"\n')
    received = work / "received.jsonl"
    with received.open("w") as out:
        sub = subprocess.Popen([sys.executable, str(SUBSCRIBER), "--listen", f"tcp/127.0.0.1:{port}", "--json",
                                "--idle", "3", "--seconds", str(args.seconds + 120)], stdout=out,
                               stderr=subprocess.PIPE, text=True)
        assert sub.stderr is not None and "listening" in sub.stderr.readline()
        run = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "run", "--board", str(board), "--duration",
                              str(args.seconds)], capture_output=True, text=True, check=False)
        sub.wait()
    if run.returncode != 0:
        print(run.stderr[-2000:], file=sys.stderr)
        return 1
    found = re.search(r"processed (\d+) frames", run.stdout)
    assert found, run.stdout
    n = int(found.group(1))
    messages = [json.loads(line) for line in received.read_text().splitlines() if line.strip()]
    contacts = [m for m in messages if m["topic"] == "/optitac/thumb/contacts"]
    rows = expected_csv(presses, bundle, n, work / "contacts.csv")
    frames = [m["message"]["frame"] for m in contacts]
    bad = [(m["message"]["frame"], why) for m in contacts
           if m["message"]["frame"] < n and (why := differs(m["message"], rows[m["message"]["frame"]]))]
    late = np.array([m["received_ns"] - m["message"]["t_ns"] for m in contacts], dtype=np.float64) / 1e6
    with_contact = sum(1 for m in contacts if m["message"]["contacts"])
    print(f"run: {n} frames processed in {args.seconds:.0f} s at {args.fps:.0f} fps; "
          f"{run.stdout.strip().splitlines()[-1].strip()}")
    print(f"received: {len(contacts)} Contacts messages ({with_contact} with contacts, "
          f"{sum(len(m['message']['contacts']) for m in contacts)} contacts), missing {n - len(set(frames))}, "
          f"in order {frames == sorted(frames)}, SensorStatus {sum(m['topic'].endswith('/status') for m in messages)}")
    print(f"against the contacts CSV of the same frames: {len(bad)} frames differ" +
          (f" (first: frame {bad[0][0]}: {bad[0][1]})" if bad else ""))
    print(f"latency capture -> subscriber: p50 {np.percentile(late, 50):.2f} ms, p99 "
          f"{np.percentile(late, 99):.2f} ms, max {late.max():.2f} ms")
    print(f"files in {work}")
    return 0 if not bad and len(set(frames)) == n else 1


if __name__ == "__main__":
    sys.exit(main())
