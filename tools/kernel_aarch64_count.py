"""Instructions per frame of the compiled kernel alone on aarch64, counted under qemu-user.

Usage::

    python tools/kernel_aarch64_count.py --harness ./harness-aarch64 [--workdir DIR] [--frames 8]

``harness-aarch64`` is kernel/harness.c built as ``tools/kernel_aarch64.sh`` builds it (static, Debian's
``aarch64-linux-gnu-gcc``, the flags of setup.py). For each configuration (gray 217 fibres with 0, 1 and 4
presses; RGB with one; 1027 fibres with one) it writes the kernel's plan and ``F`` then ``2F`` frames
after the baseline (tools/kernel_aarch64.py's format) and runs the harness under
``qemu-aarch64 -d in_asm,exec,nochain``: qemu logs every translated block with its instructions and
every block it executes, so the instructions executed are the sum over the executed blocks of their
lengths. The difference of the two runs over ``F`` is the count per frame, the harness's start and
reading cancelled. The same method on x86-64 (callgrind of the harness) is docs/performance.md's
"kernel alone" table; the x86 counts of the whole ``Pipeline.process`` are tools/callgrind_frame.py's.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

#: Rest frames before the presses of each configuration's frames.
REST = 30
_BLOCK = re.compile(r"^0x([0-9a-f]+):\s")
_TRACE = re.compile(r"^Trace \d+: 0x[0-9a-f]+ \[[0-9a-f]+/([0-9a-f]+)/")


def count_by_block(log: Path) -> dict[int, int]:
    """Instructions executed in each translated block (by its first address), from a qemu
    ``-d in_asm,exec,nochain`` log."""
    size: dict[int, int] = {}
    total: dict[int, int] = {}
    block_pc: int | None = None
    block_len = 0
    with log.open() as f:
        for line in f:
            if line.startswith("IN:"):
                if block_pc is not None:
                    size[block_pc] = block_len
                block_pc, block_len = None, 0
                continue
            m = _BLOCK.match(line)
            if m:
                if block_pc is None:
                    block_pc = int(m.group(1), 16)
                block_len += 1
                continue
            t = _TRACE.match(line)
            if t:
                if block_pc is not None:  # the block just translated is complete
                    size[block_pc] = block_len
                    block_pc, block_len = None, 0
                pc = int(t.group(1), 16)
                total[pc] = total.get(pc, 0) + size.get(pc, 0)
    return total


def by_function(blocks: dict[int, int], harness: str) -> dict[str, int]:
    """``blocks`` summed by the function each block starts in (the harness's symbols, ``nm -n``)."""
    import bisect

    nm = subprocess.run(["aarch64-linux-gnu-nm", "-n", harness], check=True, capture_output=True, text=True).stdout
    symbols = [(int(a, 16), name) for a, kind, name in (line.split()[:3] for line in nm.splitlines()
                                                        if len(line.split()) >= 3) if kind in "tTwW"]
    starts = [a for a, _ in symbols]
    out: dict[str, int] = {}
    for pc, n in blocks.items():
        i = bisect.bisect_right(starts, pc) - 1
        name = symbols[i][1] if i >= 0 else "?"
        out[name] = out.get(name, 0) + n
    return out


def _configs(workdir: Path) -> list[tuple[str, Any, list[Any]]]:
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.sim.bundles import cached_layout_bundle, cached_sim_bundle
    from optitac_edge.sim.multi_press import multi_press_frames

    gray = load_bundle(cached_sim_bundle(workdir))
    rgb = load_bundle(cached_sim_bundle(workdir, rgb=True))
    big = load_bundle(cached_layout_bundle(workdir, 18))
    out = []
    for k in (0, 1, 4):
        out.append((f"gray-217-{k}", gray,
                    multi_press_frames(k, 90, REST, layout=gray.layout, fps=240.0, seed=k)))
    out.append(("rgb-217-1", rgb,
                multi_press_frames(1, 90, REST, layout=rgb.layout, rgb=True, fps=240.0, seed=1)))
    out.append(("gray-1027-1", big,
                multi_press_frames(1, 90, REST, layout=big.layout, fps=240.0, seed=1)))
    return out


def _run(harness: str, bundle: Any, frames: list[Any], n: int, workdir: Path, name: str) -> dict[int, int]:
    from kernel_aarch64 import write_vectors  # tools/, the script's own directory

    from optitac_edge.core.pipeline import Pipeline

    pipe = Pipeline(bundle, compiled=True)
    period = 4_166_667
    k = 0
    while not pipe.baseline_ready:
        pipe.process_recorded(frames[k], k * period)
        k += 1
    pressed = frames[REST:]  # multi_press_frames: REST frames at rest, then the presses held
    rest = [pressed[i % len(pressed)] for i in range(n)]
    vectors, out, log = (workdir / f"{name}-{n}.{ext}" for ext in ("okv", "out", "log"))
    write_vectors(pipe, rest, [(k + i) * period for i in range(n)], vectors)
    subprocess.run(["qemu-aarch64", "-d", "in_asm,exec,nochain", "-D", str(log), harness, str(vectors), str(out)],
                   check=True)
    try:
        return count_by_block(log)
    finally:
        log.unlink()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--harness", required=True, help="kernel/harness.c built for aarch64")
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "optitac-bench")
    ap.add_argument("--frames", type=int, default=8, help="F: frames of the difference")
    ap.add_argument("--only", default=None, help="comma-separated configuration names")
    ap.add_argument("--by-function", type=int, default=0, metavar="N",
                    help="also the N functions with the most instructions per frame")
    args = ap.parse_args(argv)
    args.workdir.mkdir(parents=True, exist_ok=True)
    wanted = None if args.only is None else set(args.only.split(","))
    for name, bundle, frames in _configs(args.workdir):
        if wanted is not None and name not in wanted:
            continue
        a = _run(args.harness, bundle, frames, args.frames, args.workdir, name)
        b = _run(args.harness, bundle, frames, 2 * args.frames, args.workdir, name)
        per_frame = (sum(b.values()) - sum(a.values())) / args.frames
        print(f"{name}: {per_frame:,.0f} aarch64 instructions per frame (kernel alone)", flush=True)
        if args.by_function:
            fa, fb = by_function(a, args.harness), by_function(b, args.harness)
            rows = sorted(((fb.get(f, 0) - fa.get(f, 0)) / args.frames, f) for f in set(fa) | set(fb))
            for n, f in reversed(rows[-args.by_function:]):
                print(f"    {f}: {n:,.0f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
