"""Instructions, numpy buffers and libc mallocs per frame, counted by valgrind's callgrind.

Usage::

    python tools/callgrind_frame.py [--workdir DIR] [--frames 200] [--json callgrind.json]

For each configuration (gray 640x480, 217 fibers with 0, 1, 2 and 4 contacts;
1027 fibers with one contact; RGB with one contact) it pre-renders the
frames, then runs a small driver under ``valgrind --tool=callgrind`` twice:
with ``W + F`` and ``W + 2F`` frames after the same warm-up ``W`` (every
distinct frame once). The difference of the two runs divided by ``F`` is the
per-frame count, with start-up, imports and warm-up cancelled exactly:

* ``instructions``: instructions executed (``Ir``) per frame, repeatable to
  a fraction of a percent on a noisy machine (it counts, not times);
* ``numpy_buffers``: calls of numpy's data allocator (``PyDataMem_UserNEW``)
  per frame, i.e. gross numpy buffers, including temporaries freed within the
  frame (tracemalloc sees only net bytes);
* ``mallocs``: libc ``malloc`` calls per frame (numpy's small-buffer cache,
  Python's allocator, OpenCV's).

The driver does what the service's thread does per frame apart from the
camera hand-off: :meth:`~optitac_edge.core.pipeline.Pipeline.process` (the frame check, whose kernel
reads the pixels after the fiber means, and the frame),
the outbox's messages (protocol v1: the CONTACT) and their wire encoding. Needs valgrind on the PATH; docs/performance.md has the
results and the Pi projection made from them.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

#: (name, rings, pixel format, contacts).
CONFIGS = (("gray-217-0", 8, "gray", 0), ("gray-217-1", 8, "gray", 1), ("gray-217-2", 8, "gray", 2),
           ("gray-217-4", 8, "gray", 4), ("gray-1027-1", 18, "gray", 1), ("rgb-217-1", 8, "rgb", 1))
#: Functions whose calls are counted.
COUNTED = {"numpy_buffers": "PyDataMem_UserNEW", "mallocs": "malloc"}


def driver(bundle_path: str, frames_path: str, rest: int, n: int, backend: str = "compiled", what: str = "service") -> None:
    """Run under callgrind: warm up on every frame once, then ``n`` more frames (cycled).

    ``backend``: the compiled kernel or the numpy parts; ``what``: the service's work per frame (frame
    check, pipeline, outbox, encoding) or :meth:`Pipeline.process_recorded` alone."""
    import numpy as np

    from optitac_edge.core.frame_engine import Skip
    from optitac_edge.core.pipeline import Pipeline, single_threaded_opencv
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.protocol.outbox import LinkState, SensorOutbox
    from optitac_edge.io.protocol.wire import encode_frame

    bundle = load_bundle(bundle_path)
    frames = list(np.load(frames_path))
    pipe = Pipeline(bundle, compiled=backend == "compiled")
    outbox = SensorOutbox(0)
    link = LinkState()
    period = 4_166_667
    t = 0

    def one(frame: np.ndarray, t_ns: int) -> None:
        if what == "process":
            pipe.process_recorded(frame, t_ns)
            return
        result = pipe.process(frame, t_ns)
        if isinstance(result, Skip):  # dark or saturated: skipped
            return
        for packet in outbox.update(result, link, True, t_ns):  # packed for a serial link, then framed
            encode_frame(packet.kind, 0, packet.t_us, packet.frames[0][1])

    with single_threaded_opencv():
        for f in frames:
            one(f, t)
            t += period
        cycle = frames[rest:]
        for i in range(n):
            one(cycle[i % len(cycle)], t)
            t += period


def parse(path: Path) -> dict[str, int]:
    """Total instructions and the calls of each :data:`COUNTED` function in a callgrind output file."""
    names: dict[str, str] = {}
    calls: dict[str, int] = defaultdict(int)
    total = 0
    callee = None
    ref = re.compile(r"^c?fn=\((\d+)\)(?: (.*))?$")
    with path.open() as f:
        for line in f:
            if line.startswith(("fn=", "cfn=")):
                m = ref.match(line.rstrip("\n"))
                if m:
                    key, name = m.group(1), m.group(2)
                    if name:
                        names[key] = name
                    fn_name = names.get(key, "")
                else:
                    fn_name = line.split("=", 1)[1].strip()
                callee = fn_name if line.startswith("cfn=") else None
            elif line.startswith("calls=") and callee is not None:
                calls[callee] += int(line.split("=", 1)[1].split()[0])
            elif line.startswith(("summary:", "totals:")):
                total = max(total, int(line.split()[1]))
    return {"instructions": total, **{k: calls.get(v, 0) for k, v in COUNTED.items()}}


def run_callgrind(bundle: Path, frames: Path, rest: int, n: int, out: Path, backend: str = "compiled",
                  what: str = "service") -> dict[str, int]:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    cmd = ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", "--dump-instr=no",
           "--compress-strings=yes", "--separate-threads=no", sys.executable, __file__, "--driver",
           str(bundle), str(frames), str(rest), str(n), backend, what]
    subprocess.run(cmd, check=True, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return parse(out)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--driver":
        driver(argv[1], argv[2], int(argv[3]), int(argv[4]), argv[5], argv[6])
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "optitac-bench")
    ap.add_argument("--frames", type=int, default=200, help="F: frames of the difference (default 200)")
    ap.add_argument("--json", type=Path, default=Path("callgrind.json"))
    ap.add_argument("--only", default=None, help="comma-separated configuration names")
    ap.add_argument("--backend", choices=("compiled", "numpy"), default="compiled",
                    help="the compiled kernel (default) or the numpy pipeline")
    ap.add_argument("--what", choices=("service", "process"), default="service",
                    help="the service's work per frame (default: check, pipeline, outbox, encoding) or "
                         "Pipeline.process alone")
    args = ap.parse_args(argv)
    import numpy as np

    from optitac_edge.devtools.bench.scaling import DISTINCT_FRAMES, REST_FRAMES
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.sim.bundles import cached_layout_bundle, cached_sim_bundle
    from optitac_edge.sim.multi_press import multi_press_frames

    wanted = set(args.only.split(",")) if args.only else None
    results = {}
    with tempfile.TemporaryDirectory(prefix="optitac-callgrind-") as tmp:
        for name, rings, fmt, contacts in CONFIGS:
            if wanted is not None and name not in wanted:
                continue
            rgb = fmt == "rgb"
            bundle = (cached_sim_bundle(args.workdir, rgb=rgb) if rings == 8
                      else cached_layout_bundle(args.workdir, rings, rgb=rgb))
            layout = load_bundle(bundle).layout
            frames = multi_press_frames(contacts, DISTINCT_FRAMES, REST_FRAMES, layout=layout, rgb=rgb,
                                        fps=240.0, seed=contacts)
            frames_path = Path(tmp) / f"{name}.npy"
            np.save(frames_path, np.stack(frames))
            t0 = time.monotonic()
            a = run_callgrind(bundle, frames_path, REST_FRAMES, args.frames, Path(tmp) / f"{name}-a.out",
                              args.backend, args.what)
            b = run_callgrind(bundle, frames_path, REST_FRAMES, 2 * args.frames, Path(tmp) / f"{name}-b.out",
                              args.backend, args.what)
            per = {k: round((b[k] - a[k]) / args.frames, 1) for k in a}
            results[name] = {"fibers": layout.n_fibers, "pixel_format": fmt, "contacts": contacts, **per}
            print(f"{name}: {per['instructions']:,.0f} instructions, {per['numpy_buffers']} numpy buffers, "
                  f"{per['mallocs']} mallocs per frame ({time.monotonic() - t0:.0f} s)", flush=True)
    args.json.write_text(json.dumps({"frames": args.frames, "backend": args.backend, "what": args.what,
                                     "configs": results}, indent=1) + "\n")
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
