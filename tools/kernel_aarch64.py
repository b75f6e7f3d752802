"""The compiled kernel on another architecture: its plan and frames out to the C harness, the results back.

Usage (tools/kernel_aarch64.sh runs it with both harness builds)::

    python tools/kernel_aarch64.py --workdir DIR --harness ./harness-x86_64 --harness "qemu-aarch64 ./harness-aarch64"

For each configuration (gray 217 fibers with 0, 1, 2 and 4 presses, an LED dimming and every calibration
model; RGB with one press; 1027 fibers with one press) it runs the compiled pipeline here through the
baseline, writes the kernel's plan and state and the following frames to a file (kernel/harness.c's
format), runs each harness on it and compares every frame's contacts with this machine's kernel:
identical counts; centroid and widths within 1e-6 mm, angle 1e-3 degrees, everything else within 1e-9
relative (the libm of another machine may round exp, log, atan2 differently in the last bit). It prints
how many values were bit-identical. tests/test_kernel.py uses the same functions on a small
configuration in CI.
"""

from __future__ import annotations

import argparse
import math
import shlex
import struct
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from optitac_edge.core._frame_kernel import FIELD_NAMES  # the columns of a contact (kernel/frame_kernel.h)

#: The columns' tolerances: absolute for mm and degrees.
ABSOLUTE = {"x_mm": 1e-6, "y_mm": 1e-6, "major_mm": 1e-6, "minor_mm": 1e-6, "angle_deg": 1e-3}
RELATIVE = 1e-9
_KINDS = {np.dtype(np.float32): b"f", np.dtype(np.float64): b"d", np.dtype(np.int32): b"i",
          np.dtype(np.int64): b"q", np.dtype(np.uint8): b"b"}


def _entry(name: str, value: Any) -> bytes:
    if np.ndim(value) == 0:  # a scalar: one float64
        arr = np.asarray([value], dtype=np.float64)
    else:
        arr = np.ascontiguousarray(value)
    kind = _KINDS[arr.dtype]
    raw = name.encode()
    return struct.pack("<H", len(raw)) + raw + kind + struct.pack("<Q", arr.size) + arr.tobytes()


def write_vectors(pipe: Any, frames: list[np.ndarray], times: list[int], path: Path) -> np.ndarray:
    """The kernel of ``pipe`` (past its baseline, before ``frames``) and the frames to ``path``; runs the frames
    here and returns every frame's contacts as the harness writes them (a flat float64 array per frame in a
    list is awkward: an object array of (n, FIELDS) arrays).

    Raises
    ------
    ValueError
        If the pipeline has no kernel, is not past its baseline, or a frame raised fibers (the harness
        does not do the Python side's raise).
    """
    from optitac_edge.core.compiled import CompiledEngine

    fk = pipe.engine
    if not isinstance(fk, CompiledEngine) or not pipe.baseline_ready:
        raise ValueError("the pipeline must run the kernel and be past its baseline")
    kern, levels = fk.kernel, pipe.levels
    state = {"state_trunc": float(levels.trunc), "state_off": float(levels.off), "state_on": float(levels.on),
             "state_gain_delta": levels.gain_delta, "state_gain_tolerance": levels.gain_tolerance,
             "state_gain_significant": levels.gain_significant, "state_reference_ns": float(kern.reference_ns),
             "state_correct": float(kern.correct), "state_last_ns": float(pipe._last_ns or 0),
             "frames": np.concatenate([f.reshape(-1) for f in frames]), "times": np.asarray(times, dtype=np.int64)}
    with open(path, "wb") as out:
        out.write(b"OKV1")
        out.writelines(_entry(name, value) for name, value in {**fk.plan.as_dict(), **state}.items())
    expected = np.empty(len(frames), dtype=object)
    for k, (frame, t) in enumerate(zip(frames, times)):
        result = pipe.process_recorded(frame, t)
        if kern.raise_pending:
            raise ValueError(f"frame {k} raised fibers: not a frame for the harness")
        expected[k] = fk.contacts[:result.n_contacts].copy()
    return expected


def read_results(path: Path, n_frames: int, fields: int = len(FIELD_NAMES)) -> np.ndarray:
    """The harness's output: every frame's contacts, (n, fields) float64 each."""
    data = path.read_bytes()
    out = np.empty(n_frames, dtype=object)
    at = 0
    for k in range(n_frames):
        (n,) = struct.unpack_from("<i", data, at)
        at += 4
        out[k] = np.frombuffer(data, dtype=np.float64, count=n * fields, offset=at).reshape(n, fields)
        at += 8 * n * fields
    if at != len(data):
        raise ValueError(f"{path}: {len(data) - at} bytes after the last frame")
    return out


def compare(expected: np.ndarray, got: np.ndarray) -> tuple[list[str], int, int]:
    """(every disagreement beyond the tolerances, values compared, values bit-identical)."""
    problems: list[str] = []
    n_values = identical = 0
    for k, (a, b) in enumerate(zip(expected, got)):
        if a.shape != b.shape:
            problems.append(f"frame {k}: {len(a)} contacts here, {len(b)} there")
            continue
        for i in range(a.shape[0]):
            for j, name in enumerate(FIELD_NAMES):
                x, y = float(a[i, j]), float(b[i, j])
                n_values += 1
                if x == y or (math.isnan(x) and math.isnan(y)):
                    identical += 1
                    continue
                tol = ABSOLUTE.get(name, RELATIVE * max(abs(x), 1.0))
                if name == "angle_deg":
                    off = abs((x - y + 90.0) % 180.0 - 90.0)
                else:
                    off = abs(x - y)
                if not off <= tol:
                    problems.append(f"frame {k} contact {i} {name}: {x!r} here, {y!r} there")
    return problems, n_values, identical


def run_harness(command: str, vectors: Path, out: Path) -> None:
    subprocess.run([*shlex.split(command), str(vectors), str(out)], check=True)


def _configs(workdir: Path) -> list[tuple[str, Any, list[np.ndarray]]]:
    from optitac_edge.core.pipeline import Pipeline
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.sim.bundles import cached_layout_bundle, cached_sim_bundle
    from optitac_edge.sim.multi_press import multi_press_frames

    out = []
    gray = load_bundle(cached_sim_bundle(workdir))
    frames = [f for k in (0, 1, 2, 4) for f in multi_press_frames(k, 60, 30 if k == 0 else 2, layout=gray.layout,
                                                                      fps=240.0, seed=k)]
    dim = [np.clip(np.rint(f.astype(np.float32) * (1.0 - 0.06 * i / 60)), 0, 255).astype(np.uint8)
           for i, f in enumerate(multi_press_frames(1, 60, 0, layout=gray.layout, fps=240.0, seed=9))]
    out.append(("gray-217", Pipeline(gray, compiled=True), frames + dim))
    rgb = load_bundle(cached_sim_bundle(workdir, rgb=True))
    out.append(("rgb-217", Pipeline(rgb, compiled=True),
                multi_press_frames(1, 80, 30, layout=rgb.layout, rgb=True, fps=240.0, seed=1)))
    big = load_bundle(cached_layout_bundle(workdir, 18))
    out.append(("gray-1027", Pipeline(big, compiled=True),
                multi_press_frames(1, 60, 30, layout=big.layout, fps=240.0, seed=1)))
    return out


def check(pipe: Any, frames: list[np.ndarray], harnesses: list[str], workdir: Path, name: str,
          period_ns: int = 4_166_667) -> list[str]:
    """Run ``frames`` through ``pipe`` up to its baseline, the rest here and through each harness; the lines
    to print (a disagreement starts with 'MISMATCH')."""
    k = 0
    while not pipe.baseline_ready:
        pipe.process_recorded(frames[k], k * period_ns)
        k += 1
    rest = frames[k:]
    times = [(k + i) * period_ns for i in range(len(rest))]
    vectors = workdir / f"{name}.okv"
    expected = write_vectors(pipe, rest, times, vectors)
    lines = []
    for command in harnesses:
        out = workdir / f"{name}.{Path(shlex.split(command)[-1]).name}.out"
        run_harness(command, vectors, out)
        problems, n_values, identical = compare(expected, read_results(out, len(rest)))
        contacts = sum(len(e) for e in expected)
        lines.append(f"{name} [{command}]: {len(rest)} frames, {contacts} contacts, {n_values} values, "
                     f"{identical} bit-identical, {len(problems)} beyond the tolerances")
        lines += [f"MISMATCH {p}" for p in problems[:20]]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "optitac-bench")
    ap.add_argument("--harness", action="append", required=True,
                    help="a command running kernel/harness.c's build (repeatable), e.g. 'qemu-aarch64 ./h'")
    args = ap.parse_args(argv)
    args.workdir.mkdir(parents=True, exist_ok=True)
    failed = False
    for name, pipe, frames in _configs(args.workdir):
        for line in check(pipe, frames, args.harness, args.workdir, name):
            print(line, flush=True)
            failed |= line.startswith("MISMATCH")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
