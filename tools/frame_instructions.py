#!/usr/bin/env python3
"""Instructions per frame of the pipeline, counted by valgrind (repeatable on a noisy machine).

    python tools/frame_instructions.py [--cal BUNDLE] [--recording REC] [--frames 200] [--extra 200]

Runs the same process under ``valgrind --tool=callgrind`` twice, processing
``frames`` and then ``frames + extra`` frames of the recording (after its rest
frames and one warm-up pass), and prints the difference of the two instruction
totals divided by ``extra``: the instructions one frame costs, start-up and
imports cancelled out. Without ``--cal``/``--recording`` it builds the
simulated sensor's bundle with every model and an ``unseen`` recording in
``--workdir``. Needs valgrind.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path


def process(cal: str, rec: str, frames: int) -> None:
    """The measured program: warm up over the recording once, then process ``frames`` frames."""
    from optitac_edge.core.pipeline import Pipeline, single_threaded_opencv
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.recording import Recording

    recording = Recording(rec)
    pipe = Pipeline(load_bundle(cal))
    period = int(1e9 / recording.meta.fps)
    rest = recording.meta.rest_frames
    all_frames = [recording.frame(i).copy() for i in range(len(recording))]
    t = 0
    with single_threaded_opencv():
        for f in all_frames:  # baseline, then every frame once
            pipe.process(f, t)
            t += period
        loop = all_frames[rest:]
        for i in range(frames):
            pipe.process(loop[i % len(loop)], t)
            t += period


def instructions(cal: str, rec: str, frames: int, out_dir: Path) -> int:
    out = out_dir / f"callgrind.{frames}"
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "PYTHONHASHSEED": "0"}
    subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", sys.executable,
                    __file__, "--child", cal, rec, str(frames)], env=env, check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    summary = re.search(r"^summary:\s+(\d+)", out.read_text(), re.MULTILINE)
    if summary is None:
        raise SystemExit(f"no summary in {out}")
    return int(summary.group(1))


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        process(sys.argv[2], sys.argv[3], int(sys.argv[4]))
        return 0
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cal", default=None, help="bundle (default: the simulated sensor's, built in --workdir)")
    p.add_argument("--recording", default=None, help="recording (default: a simulated 'unseen' one)")
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--extra", type=int, default=200)
    p.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "optitac-instructions")
    args = p.parse_args()
    if shutil.which("valgrind") is None:
        print("frame_instructions: valgrind not found", file=sys.stderr)
        return 2
    args.workdir.mkdir(parents=True, exist_ok=True)
    cal, rec = args.cal, args.recording
    if cal is None:
        from optitac_edge.sim.bundles import cached_sim_bundle

        cal = str(cached_sim_bundle(args.workdir))
    if rec is None:
        from optitac_edge.sim.scenarios import write_scenario

        rec = str(args.workdir / "unseen")
        if not (Path(rec) / "meta.json").exists():
            write_scenario(rec, "unseen", seed=1)
    a = instructions(cal, rec, args.frames, args.workdir)
    b = instructions(cal, rec, args.frames + args.extra, args.workdir)
    print(f"{(b - a) / args.extra:.0f} instructions per frame ({args.extra} frames: {a} -> {b})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
