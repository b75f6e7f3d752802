"""How the loop's cost moves with what it sees: simultaneous contacts, fiber count, the reference, the heap.

Every section runs its configurations interleaved frame by frame (see
:mod:`optitac_edge.devtools.bench.paced`), so a ratio between two of them is
measured under the same load.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from optitac_edge.core.frame_result import FrameResult
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.devtools.bench.paced import Paced, ratio, run_interleaved

if TYPE_CHECKING:
    from optitac_edge.core.bundle import CalibrationBundle
    from optitac_edge.core.layout import FiberLayout

#: Simultaneous contacts the bench presses.
CONTACT_COUNTS = (0, 1, 2, 4)
#: Hexagonal rings of the fiber-count comparison: 217, 469 and 1027 fibers.
FIBER_RINGS = (8, 12, 18)
#: Distinct frames per configuration (cycled): ~300 kB each, so they are cold in the caches as a camera's.
DISTINCT_FRAMES = 240
#: Leading contact-free frames (the baseline) of each configuration.
REST_FRAMES = 12


def contact_frames(n_contacts: int, rgb: bool, fps: float, layout: FiberLayout | None = None) -> list[np.ndarray]:
    """Rest frames, then :data:`DISTINCT_FRAMES` frames with ``n_contacts`` indenters pressed throughout."""
    from optitac_edge.sim.multi_press import multi_press_frames

    return multi_press_frames(n_contacts, DISTINCT_FRAMES, REST_FRAMES, layout=layout, rgb=rgb, fps=fps,
                              seed=n_contacts)


def _count(result: FrameResult) -> int:
    return result.n_contacts


def measure_contacts(bundle: CalibrationBundle, fps: float, n: int, rgb: bool) -> dict[str, Any]:
    """0, 1, 2 and 4 simultaneous contacts, paced at ``fps`` and interleaved; ratios to one contact."""
    configs = [Paced(f"{k}", Pipeline(bundle).process_recorded, contact_frames(k, rgb, fps), REST_FRAMES, _count)
               for k in CONTACT_COUNTS]
    res = run_interleaved(configs, fps, n, warmup_per_config=min(100, n))
    return {"fps": fps, "frames_per_config": n, "per_contacts": res,
            "ratio_0_to_1": ratio(res["0"], res["1"]), "ratio_2_to_1": ratio(res["2"], res["1"]),
            "ratio_4_to_1": ratio(res["4"], res["1"])}


def measure_fibers(workdir: Path, fps: float, n: int, rgb: bool) -> dict[str, Any]:
    """One contact on 217, 469 and 1027-fiber arrays at the same frame size (fiber-map bundles), interleaved."""
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.sim.bundles import cached_layout_bundle

    configs = []
    for rings in FIBER_RINGS:
        bundle = load_bundle(cached_layout_bundle(workdir, rings, rgb=rgb))
        configs.append(Paced(str(bundle.fibers.n_fibers), Pipeline(bundle).process_recorded,
                             contact_frames(1, rgb, fps, bundle.layout), REST_FRAMES, _count))
    res = run_interleaved(configs, fps, n, warmup_per_config=min(100, n))
    names = [c.name for c in configs]
    return {"fps": fps, "frames_per_config": n, "per_fibers": res,
            "ratio_largest_to_smallest": ratio(res[names[-1]], res[names[0]])}


def measure_reference(bundle: CalibrationBundle, frames: list[np.ndarray], rest: int, n: int) -> dict[str, Any]:
    """The paper's method done literally against the fast pipeline in paper mode, interleaved frame by frame.

    Unpaced: the reference takes longer than a camera period, and its working set
    (tens of MB) leaves the fast pipeline's tables cold for every one of its frames,
    as other work on a board would.
    """
    from optitac_edge.core.options import ContactOptions
    from optitac_edge.devtools.reference import ReferencePipeline

    fast = Pipeline(bundle, ContactOptions.paper())
    fast.set_corrector(None)
    configs = [Paced("reference", ReferencePipeline(bundle).process, frames, rest),
               Paced("fast_paper_mode", fast.process_recorded, frames, rest),
               Paced("fast_all_options", Pipeline(bundle).process_recorded, frames, rest)]
    res = run_interleaved(configs, 0.0, n, warmup_per_config=min(20, n))
    return {"frames": n, "reference": res["reference"], "fast_paper_mode": res["fast_paper_mode"],
            "fast_all_options": res["fast_all_options"],
            "ratio_reference_to_fast_paper_mode": ratio(res["reference"], res["fast_paper_mode"]),
            "ratio_reference_to_fast_all_options": ratio(res["reference"], res["fast_all_options"])}


class _Mallinfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
                 "fordblks", "keepcost")]


def libc_heap() -> dict[str, int] | None:
    """glibc's heap: bytes in use (``uordblks`` + mmapped ``hblkhd``) and the arena size; None elsewhere."""
    name = ctypes.util.find_library("c")
    try:
        fn = ctypes.CDLL(name).mallinfo2
    except (OSError, AttributeError, TypeError):
        return None
    fn.restype = _Mallinfo2
    m = fn()
    return {"in_use": int(m.uordblks + m.hblkhd), "arena": int(m.arena + m.hblkhd)}


def measure_heap(bundle: CalibrationBundle, fps: float, n: int, rgb: bool) -> dict[str, Any]:
    """glibc heap growth over ``n`` steady-state frames per contact count (after one pass over its frames)."""
    period = int(1e9 / fps)
    out: dict[str, Any] = {"frames_per_config": n}
    if libc_heap() is None:
        return {"skipped": "glibc's mallinfo2 is not available"}
    for k in CONTACT_COUNTS:
        frames = contact_frames(k, rgb, fps)
        pipe = Pipeline(bundle)
        t = 0
        for f in frames:  # baseline, then every distinct frame once
            pipe.process_recorded(f, t)
            t += period
        cycle = frames[REST_FRAMES:]
        before = libc_heap()
        for i in range(n):
            pipe.process_recorded(cycle[i % len(cycle)], t)
            t += period
        after = libc_heap()
        assert before is not None and after is not None
        out[str(k)] = {"in_use_growth_bytes": after["in_use"] - before["in_use"],
                       "arena_growth_bytes": after["arena"] - before["arena"]}
    return out


def measure_service_cpu(cal: Path, fps: float, seconds: float, rounds: int, rgb: bool,
                        log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """The service's main-thread CPU per frame with 0, 1, 2 and 4 contacts; ``rounds`` passes, interleaved.

    Each pass runs the production loop (:func:`measure_end_to_end`) ``seconds`` long per
    contact count, in the order 1, 0, 2, 4; the figure per count is the median over the passes.
    """
    from optitac_edge.devtools.bench.end_to_end import EndToEnd, measure_end_to_end

    frames = {k: contact_frames(k, rgb, fps) for k in CONTACT_COUNTS}
    runs: dict[str, list[dict[str, Any]]] = {str(k): [] for k in CONTACT_COUNTS}
    for r in range(rounds):
        for k in (1, 0, 2, 4):
            e = measure_end_to_end(EndToEnd(cal, fps, seconds, rgb, frames[k], REST_FRAMES))
            runs[str(k)].append({"main_thread": e["main_thread"], "frames_dropped": e["frames_dropped"],
                                 "latency_us": e["latency_us"]})
            if log is not None and e["main_thread"]:
                log(f"  service, {k} contact(s), pass {r + 1}: "
                    f"{e['main_thread']['cpu_us_per_frame']} µs main-thread CPU per frame")
    med = {k: _median([v["main_thread"]["cpu_us_per_frame"] for v in vs if v["main_thread"]])
           for k, vs in runs.items()}
    return {"fps": fps, "seconds": seconds, "rounds": rounds, "runs": runs,
            "cpu_us_per_frame": med,
            "ratio_0_to_1": _div(med["0"], med["1"]), "ratio_4_to_1": _div(med["4"], med["1"])}


def _median(values: list[float]) -> float | None:
    return round(float(np.median(values)), 1) if values else None


def _div(a: float | None, b: float | None) -> float | None:
    return round(a / b, 3) if a and b else None
