"""``optitac-edge bench``: how fast the per-frame loop is, measured, in one run.

Sections (all on the same frames, one process unless noted; see docs/performance.md):

``stages``
    The real :meth:`Pipeline.process_recorded` call timed per frame (``whole_frame``), and
    each stage re-run in isolation on that frame's state right after it
    (``gray``: gather of the fiber pixels, luma for RGB; ``fiber_means``: the
    segmented sum; ``baseline``: the signal against the baseline, gain
    compensation included; ``surface``; ``segment``: truncation and the
    multi-contact partition; ``moments``; ``hu`` (Hu and q4 of the binarised
    contact); ``shape``: the shape model; ``calibration``: centroid map and
    width model lookup; ``encode``: CONTACT message fill and wire encoding).
    Stages that do not run on a frame (no contact, model absent) are not
    sampled on it. Median, p99 and max, µs.
``contacts``
    Frames with 0, 1, 2 and 4 indenters pressed at once (the simulator's
    multi-press), paced at ``--fps`` with cold caches and interleaved frame by
    frame (:mod:`~optitac_edge.devtools.bench.paced`); ratios to one contact.
``fibers``
    One contact on 217, 469 and 1027-fiber arrays at the same frame size,
    paced and interleaved; the ratio of the largest to the smallest.
``reference``
    :class:`~optitac_edge.devtools.reference.ReferencePipeline` (the paper's method done
    the obvious way), the fast pipeline in paper mode and with all options, on
    the first ``--reference-frames`` of the same frames, interleaved frame by
    frame so that the load cancels in the ratios of medians.
``heap``
    glibc's heap in use and arena over steady-state frames with 0-4 contacts (growth, bytes).
``service_cpu``
    The service's main-thread CPU time per frame (``getrusage(RUSAGE_THREAD)``:
    capture hand-off, frame check, pipeline, encode, transport) with 0, 1, 2
    and 4 contacts, ``--cpu-seconds`` per run, ``--cpu-rounds`` interleaved passes.
``memory``
    tracemalloc: net bytes allocated per frame after warm-up (traced memory
    after minus before, divided by the frames) and the largest transient
    allocation within a frame; RSS growth over the ``stages`` pass.
``end_to_end``
    The service loop (:class:`~optitac_edge.service.loop.Service`) with the
    camera replaying frames with ``--e2e-contacts`` indenters pressed throughout
    (default 2), paced at ``--fps``, writing serial frames into a pty; a
    separate process reads the pty and timestamps each CONTACT frame's last
    byte (CLOCK_MONOTONIC, shared by both processes): latency = that time
    minus the frame's timestamp in the packet. Frames dropped (camera
    sequence gaps), packets lost (sequence gaps seen by the reader plus
    frames the transport's queue dropped).
``patches_end_to_end``
    The same with ``--patches`` patches of 217 fibers on one ``--patch-frame``
    camera: one service, a sensor per patch (ids 1..N), every patch's pipeline
    and CONTACT on each frame, one patch pressed at a time.
``startup``
    ``optitac-edge run --cal BUNDLE`` started as a new process, time from the
    spawn to the first packet read from the pty; and, separately, the time to
    import the runtime of a board with a real camera (service, pipeline, serial link, v4l2 camera;
    no simulator) and whether scipy / scikit-learn got imported.

Runtime code must not import this module (it imports the reference, which uses scipy).
"""

from __future__ import annotations

import logging
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.pipeline import single_threaded_opencv
from optitac_edge.devtools.bench.end_to_end import EndToEnd, measure_end_to_end, measure_startup
from optitac_edge.devtools.bench.inputs import load_inputs, machine
from optitac_edge.devtools.bench.scaling import (
    contact_frames,
    measure_contacts,
    measure_fibers,
    measure_heap,
    measure_reference,
    measure_service_cpu,
)
from optitac_edge.devtools.bench.stages import STAGES, measure_memory, measure_stages

__all__ = ["STAGES", "BenchPlan", "format_table", "run_bench"]

logger = logging.getLogger(__name__)


def _published(p: dict[str, Any]) -> str:
    return (f"; published {p['published']} (dropped {p['dropped']}, errors {p['errors']}), the subscriber got "
            f"{p['received_by_subscriber']}, the Foxglove client {p['received_by_foxglove_client']}, MCAP "
            f"{p['mcap_messages']} messages")


@dataclass(frozen=True)
class BenchPlan:
    """What ``optitac-edge bench`` measures and for how long (0 turns a section off; see the module docstring).

    Attributes
    ----------
    frames : int
        Frames of the ``stages`` pass.
    source : str
        ``sim`` (the built-in sensor) or a recording.
    fps : float
        Camera rate the paced sections run at.
    cal : Path, optional
        The bundle (default: calibrated from the source).
    rgb : bool
        RGB frames (the simulator's colour camera).
    workdir : Path, optional
        Where recordings and bundles are made (default a temporary directory).
    """

    frames: int = 20000
    source: str = "sim"
    fps: float = 240.0
    cal: Path | None = None
    rgb: bool = False
    workdir: Path | None = None
    reference_frames: int = 300
    memory_frames: int = 2000
    e2e_seconds: float = 60.0
    startup: bool = True
    unique_frames: int = 600
    queue_frames: int | None = None
    view: str | None = None
    paced_frames: int = 2000
    cpu_seconds: float = 10.0
    cpu_rounds: int = 2
    e2e_contacts: int = 2
    patches: int = 4
    patch_frame: tuple[int, int] = (1280, 720)
    publish: bool = False
    workers: int | None = None


_DEFAULT_PLAN = BenchPlan()


@dataclass(frozen=True)
class _Inputs:
    """The frames and bundle every section measures on."""

    bundle: CalibrationBundle
    cal_path: Path
    frames: list[Any]
    rest: int
    workdir: Path


def run_bench(plan: BenchPlan = _DEFAULT_PLAN, log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Run every section of ``plan``; returns the results (see the module docstring).

    ``log`` gets one line per section as it finishes (default: this module's logger).
    """
    log = log or logger.info
    workdir = plan.workdir or Path(tempfile.gettempdir()) / "optitac-bench"
    t_start = time.time()
    bundle, cal_path, frame_list, described = load_inputs(plan.source, plan.cal, plan.rgb, workdir,
                                                          plan.unique_frames, plan.fps)
    rest = int(bundle.baseline_frames) if plan.source != "sim" else max(int(bundle.baseline_frames), 10)
    inputs = _Inputs(bundle, cal_path, frame_list, min(rest, len(frame_list) - 1), workdir)
    fmt = bundle.fibers.pixel_format
    h, w = bundle.fibers.height, bundle.fibers.width
    res: dict[str, Any] = {"machine": machine(), "source": described, "pixel_format": fmt,
                           "frame_size": [w, h], "bundle": str(cal_path),
                           "options": {k: getattr(bundle.options, k) for k in
                                       ("relative", "compensate_gain", "fill_dead", "max_contacts",
                                        "track_baseline", "peak_fraction", "shape_fraction")},
                           "models": sorted(k for k in ("centroid", "width", "shapes")
                                            if k in bundle.extra_meta),
                           "fibers": bundle.fibers.n_fibers, "fiber_pixels": int(bundle.fibers.pixel_index.size),
                           "mesh": bundle.grid.n}
    log(f"bench: {described}; {fmt} {w}x{h}; {plan.frames} frames")
    with single_threaded_opencv():  # as the service runs the loop
        _pipeline_sections(res, plan, inputs, log)
    sim = plan.source == "sim"
    if plan.cpu_seconds > 0 and plan.cpu_rounds > 0 and sim:
        res["service_cpu"] = sc = measure_service_cpu(cal_path, plan.fps, plan.cpu_seconds, plan.cpu_rounds,
                                                      plan.rgb, log)
        log("  service main-thread CPU per frame: " + ", ".join(
            f"{k} contacts {v} µs" for k, v in sc["cpu_us_per_frame"].items())
            + f"; 4/1 x{sc['ratio_4_to_1']}, 0/1 x{sc['ratio_0_to_1']}")
    if plan.e2e_seconds > 0:
        if not sim:
            res["end_to_end"] = {"skipped": "needs --source sim"}
        else:
            res["end_to_end"] = _end_to_end_section(plan, cal_path, log)
    if plan.e2e_seconds > 0 and plan.patches > 0 and sim and not plan.rgb:
        res["patches_end_to_end"] = _patches_end_to_end_section(plan, log)
    if plan.startup:
        if not sim or fmt != "gray":
            res["startup"] = {"skipped": "needs --source sim and gray frames (the sim board's camera)"}
        else:
            res["startup"] = s = measure_startup(cal_path, plan.fps)
            log(f"  startup: first packet after {s['start_to_first_packet_s']} s "
                f"(runtime import {s['import_runtime_s']} s; heavy modules: "
                f"{s['heavy_modules_imported'] or 'none'})")
    res["elapsed_s"] = round(time.time() - t_start, 1)
    res["machine"]["load_average_at_end"] = [round(v, 2) for v in os.getloadavg()]
    return res


def _pipeline_sections(res: dict[str, Any], plan: BenchPlan, i: _Inputs, log: Callable[[str], None]) -> None:
    """The in-process sections: stages, contacts, fibers, patches, reference, memory and heap."""
    fps, sim = plan.fps, plan.source == "sim"
    res["pipeline"] = measure_stages(i.bundle, i.frames, i.rest, plan.frames, fps)
    whole = res["pipeline"]["stages"]["whole_frame"]
    log(f"  whole frame: median {whole['median_us']} µs, p99 {whole['p99_us']} µs, max {whole['max_us']} µs")
    if plan.paced_frames > 0 and sim:
        res["contacts"] = c = measure_contacts(i.bundle, fps, plan.paced_frames, plan.rgb)
        per = c["per_contacts"]
        log(f"  contacts, paced at {fps} fps: " + ", ".join(
            f"{k}: {v['median_us']} µs" for k, v in per.items())
            + f"; 4/1 x{c['ratio_4_to_1']}, 0/1 x{c['ratio_0_to_1']}")
        res["fibers"] = fb = measure_fibers(i.workdir, fps, plan.paced_frames, plan.rgb)
        log("  fibers, one contact: " + ", ".join(f"{k}: {v['median_us']} µs" for k, v in fb["per_fibers"].items())
            + f"; x{fb['ratio_largest_to_smallest']}")
        if plan.patches > 0 and not plan.rgb:
            from optitac_edge.devtools.bench.patches import measure_patches

            pw, ph = plan.patch_frame
            res["patches"] = pt = measure_patches(plan.patches, pw, ph, fps, plan.paced_frames)
            log(f"  {plan.patches} patches of {pt['fibers_per_patch']} fibers on one {pw}x{ph} "
                f"camera, per frame: back to back {pt['back_to_back']['median_us']} µs, paced "
                f"{pt['paced']['median_us']} µs (medians)")
    if plan.reference_frames > 0:
        res["reference"] = r = measure_reference(i.bundle, i.frames, i.rest, plan.reference_frames)
        log(f"  reference (interleaved): median {r['reference']['median_us']} µs; paper mode "
            f"{r['fast_paper_mode']['median_us']} µs, x{r['ratio_reference_to_fast_paper_mode']}; "
            f"all options x{r['ratio_reference_to_fast_all_options']}")
    if plan.memory_frames > 0:
        res["memory"] = measure_memory(i.bundle, i.frames, i.rest, plan.memory_frames, fps)
        res["memory"]["rss_growth_bytes"] = res["pipeline"]["rss_growth_bytes"]
        res["memory"]["rss_frames"] = plan.frames
        log(f"  memory: {res['memory']['net_bytes_per_frame']:.1f} net bytes/frame, "
            f"RSS +{res['memory']['rss_growth_bytes']} B over {plan.frames} frames")
        if sim:
            res["heap"] = hp = measure_heap(i.bundle, fps, plan.memory_frames, plan.rgb)
            log("  libc heap growth over " + str(plan.memory_frames) + " frames: " + ", ".join(
                f"{k} contacts {v['in_use_growth_bytes']} B" for k, v in hp.items() if isinstance(v, dict)))


def _end_to_end_section(plan: BenchPlan, cal_path: Path, log: Callable[[str], None]) -> dict[str, Any]:
    """The service loop paced at the plan's rate, its packets read from a pty by another process."""
    from optitac_edge.devtools.bench.scaling import REST_FRAMES

    e = measure_end_to_end(EndToEnd(cal_path, plan.fps, plan.e2e_seconds, plan.rgb,
                                    contact_frames(plan.e2e_contacts, plan.rgb, plan.fps), REST_FRAMES,
                                    plan.queue_frames, plan.view, lambda url: log(f"  view: {url}"),
                                    publish=plan.publish))
    e["contacts_pressed"] = plan.e2e_contacts
    why = ""
    if "frames_dropped_by_pipeline" in e:
        st = e["process_stalls"]
        why = (f" (by the pipeline {e['frames_dropped_by_pipeline']}, in process stalls "
               f"{e['frames_dropped_in_process_stalls']}: {st['count']} stalls >= {st['threshold_ms']} ms, "
               f"max {st['max_ms']} ms; CPU steal {e['cpu_steal_ms']} ms)")
    log(f"  end to end @ {plan.fps} fps, {plan.e2e_seconds} s, queue {e['queue_frames']}: {e['frames']} frames, "
        f"dropped {e['frames_dropped']}{why}, lost {e['packets_lost']}, latency p50/p99/max "
        f"{e['latency_us']['p50']}/{e['latency_us']['p99']}/{e['latency_us']['max']} µs"
        + (f"; main-thread CPU {e['main_thread']['cpu_us_per_frame']} µs/frame" if e.get("main_thread") else "")
        + (f"; view updates {e['view']['updates']}, skipped {e['view']['skipped']}" if "view" in e else "")
        + (_published(e["publish"]) if "publish" in e else ""))
    return e


def _patches_end_to_end_section(plan: BenchPlan, log: Callable[[str], None]) -> dict[str, Any]:
    """The service loop over the plan's patches on one camera, one patch pressed at a time."""
    from optitac_edge.devtools.bench.patches import patch_pipelines

    pw, ph = plan.patch_frame
    pipes, patch_rest, patch_presses = patch_pipelines(plan.patches, pw, ph)
    pe = measure_end_to_end(EndToEnd(None, plan.fps, plan.e2e_seconds, False, patch_rest + patch_presses,
                                     len(patch_rest), plan.queue_frames, bundles=[p.bundle for p in pipes],
                                     publish=plan.publish, workers=plan.workers))
    pe["patches"], pe["frame_size"] = plan.patches, list(plan.patch_frame)
    log(f"  end to end, {plan.patches} patches on one {pw}x{ph} camera @ {plan.fps} fps, "
        f"{plan.e2e_seconds} s: {pe['frames']} frames, dropped {pe['frames_dropped']}"
        + (f" (by the pipeline {pe['frames_dropped_by_pipeline']})" if "frames_dropped_by_pipeline" in pe else "")
        + f", lost {pe['packets_lost']}, latency p50/p99 {pe['latency_us']['p50']}/{pe['latency_us']['p99']} µs"
        + f", {pe['sensor_workers']} sensor worker threads"
        + (f"; main-thread CPU {pe['main_thread']['cpu_us_per_frame']} µs/frame" if pe.get("main_thread")
           else "") + (_published(pe["publish"]) if "publish" in pe else ""))
    return pe


def format_table(res: dict[str, Any]) -> str:
    """The stage table as Markdown."""
    lines = ["| stage | median µs | p99 µs | max µs | frames |", "|---|---:|---:|---:|---:|"]
    for k, v in res["pipeline"]["stages"].items():
        lines.append(f"| {k} | {v['median_us']} | {v['p99_us']} | {v['max_us']} | {v['n']} |")
    return "\n".join(lines)

