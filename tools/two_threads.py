"""One Pipeline used from two threads at once, as a library user might by mistake: crashes counted.

Usage::

    python tools/two_threads.py [--runs 100] [--frames 400] [--workdir DIR]

Each run is a fresh process: two threads feed the same :class:`~optitac_edge.core.pipeline.Pipeline` (the
compiled kernel where it is built) 4-contact frames as fast as they can, through :meth:`process` and,
beside it, every other frame of the second thread straight into the engine under it (``pipeline.engine.run``, past the pipeline's own guard: the
compiled kernel's guard). A run passes when its process exits 0 and every call either returned or raised
the one clear error (:class:`~optitac_edge.errors.PipelineBusy`, the kernel's ``RuntimeError``). Before the
guards such a run segfaulted in 3 of 4 runs or hung (issue 41).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
from pathlib import Path


def worker(bundle_path: str, frames_path: str, n_frames: int) -> dict[str, int]:
    """Two threads on one pipeline: calls that returned, refused (PipelineBusy / kernel busy), other errors."""
    import numpy as np

    from optitac_edge.core.pipeline import Pipeline
    from optitac_edge.errors import PipelineBusy
    from optitac_edge.io.bundle_file import load_bundle

    frames = list(np.load(frames_path))
    pipe = Pipeline(load_bundle(bundle_path))
    period = 4_166_667
    for k, f in enumerate(frames[:12]):  # the baseline
        pipe.process(f, k * period)
    counts = {"returned": 0, "refused": 0, "other": 0}
    lock = threading.Lock()
    start = threading.Barrier(2)

    def feed(offset: int, direct: bool) -> None:
        start.wait()
        for i in range(n_frames):
            f = frames[12 + (i + offset) % (len(frames) - 12)]
            try:
                if direct and i % 2:
                    pipe.engine.run(f, (1000 + i) * period, period)
                else:
                    pipe.process(f, (1000 + i) * period)
                key = "returned"
            except PipelineBusy:
                key = "refused"
            except RuntimeError as exc:
                key = "refused" if "another thread" in str(exc) else "other"
            with lock:
                counts[key] += 1

    threads = [threading.Thread(target=feed, args=(0, False)), threading.Thread(target=feed, args=(7, True))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return counts


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--worker":
        print(json.dumps(worker(argv[1], argv[2], int(argv[3]))))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--frames", type=int, default=400, help="frames each thread feeds")
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "optitac-two-threads")
    args = ap.parse_args(argv)
    import numpy as np

    from optitac_edge.devtools.bench.scaling import contact_frames
    from optitac_edge.sim.bundles import cached_sim_bundle

    bundle = cached_sim_bundle(args.workdir)
    frames_path = args.workdir / "four-contacts.npy"
    if not frames_path.exists():
        np.save(frames_path, np.stack(contact_frames(4, False, 240.0)))
    crashes, totals = 0, {"returned": 0, "refused": 0, "other": 0}
    for _ in range(args.runs):
        proc = subprocess.run([sys.executable, __file__, "--worker", str(bundle), str(frames_path),
                               str(args.frames)], capture_output=True, text=True, timeout=300, check=False)
        if proc.returncode != 0:
            crashes += 1
            print(f"run exited {proc.returncode}: {proc.stderr.strip()[-300:]}")
            continue
        for k, v in json.loads(proc.stdout).items():
            totals[k] += v
    print(f"{args.runs} runs: {crashes} crashed; calls {totals['returned']} returned, {totals['refused']} refused "
          f"with the clear error, {totals['other']} other errors")
    return 1 if crashes or totals["other"] else 0


if __name__ == "__main__":
    raise SystemExit(main())
