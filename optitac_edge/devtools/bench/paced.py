"""Paced, interleaved timing: several pipelines take turns at the camera's rate, as a deployed board runs.

A board processes one frame per camera period and sleeps in between: its
tables and the frame are cold in the caches when the frame comes (other
processes, the kernel and the camera's DMA ran meanwhile). Back-to-back
timing hides that. Here frame ``i`` is due at ``i / fps``; the loop sleeps
until then and hands it to configuration ``i % C`` (its next frame), so all
configurations see the same machine, load and cache state, and a ratio of
their medians cancels the load (the reference against the fast pipeline,
0 against 4 contacts, 217 against 1027 fibers).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from optitac_edge.devtools.bench.samples import Samples, summary


@dataclass
class Paced:
    """One configuration of an interleaved run.

    Attributes
    ----------
    name : str
    process : callable ``(frame, t_ns) -> estimate``
        A pipeline's ``process``.
    frames : sequence of ndarray
        Its frames, cycled after ``rest`` leading contact-free frames.
    rest : int
        Leading frames fed once, unpaced and untimed (the baseline).
    count : callable ``(estimate) -> int``, optional
        How many contacts an estimate holds (recorded per frame).
    """

    name: str
    process: Callable[[np.ndarray, int], Any]
    frames: Sequence[np.ndarray]
    rest: int
    count: Callable[[Any], int] | None = None


def run_interleaved(configs: Sequence[Paced], fps: float, n_per_config: int,
                    warmup_per_config: int = 100, sleep: Callable[[float], None] = time.sleep,
                    clock_ns: Callable[[], int] = time.monotonic_ns,
                    timer_ns: Callable[[], int] = time.perf_counter_ns) -> dict[str, dict[str, Any]]:
    """Time every configuration's frames, paced at ``fps`` and taking turns frame by frame.

    Parameters
    ----------
    configs : sequence of Paced
    fps : float
        Frames per second of the whole run (each configuration gets ``fps / C``);
        0: back to back, no pacing.
    n_per_config : int
        Timed frames per configuration, after ``warmup_per_config`` untimed ones.
    sleep, clock_ns, timer_ns : callable
        The pacing's sleep and clock, and the frame timer; injected for tests.

    Returns
    -------
    dict
        Per configuration: ``summary`` of the per-frame times (µs; ``n``,
        ``median_us``, ``p99_us``, ``max_us``), ``contacts`` (the median count
        per frame, when ``count`` is given) and ``late_frames`` (frames that
        started a period or more after they were due: the machine was busy).
    """
    period_ns = int(1e9 / fps) if fps > 0 else 0
    step = len(configs) * max(period_ns, 1)  # each pipeline's own clock advances C periods a frame
    t_ns = [0] * len(configs)
    pos = [0] * len(configs)
    for k, c in enumerate(configs):
        for f in c.frames[:c.rest]:
            c.process(f, t_ns[k])
            t_ns[k] += step

    def next_frame(k: int) -> np.ndarray:
        c = configs[k]
        cycle = len(c.frames) - c.rest
        f = c.frames[c.rest + pos[k] % cycle]
        pos[k] += 1
        return f

    samples = [Samples(n_per_config) for _ in configs]
    counts = [Samples(n_per_config) for _ in configs]
    late = [0] * len(configs)
    total = len(configs) * (warmup_per_config + n_per_config)
    t0 = clock_ns()
    for i in range(total):
        k = i % len(configs)
        timed_frame = i >= len(configs) * warmup_per_config
        if period_ns:
            due = t0 + i * period_ns
            now = clock_ns()
            if due > now:
                sleep((due - now) / 1e9)
            elif timed_frame and now - due >= period_ns:
                late[k] += 1
        frame = next_frame(k)
        c = configs[k]
        start = timer_ns()
        est = c.process(frame, t_ns[k])
        elapsed = timer_ns() - start
        t_ns[k] += step
        if timed_frame:
            samples[k].append(elapsed)
            if c.count is not None:
                counts[k].append(c.count(est))
    out: dict[str, dict[str, Any]] = {}
    for k, c in enumerate(configs):
        d: dict[str, Any] = {**summary(samples[k].values), "late_frames": late[k]}
        if c.count is not None and counts[k].n:
            d["contacts"] = float(np.median(counts[k].values))
        out[c.name] = d
    return out


def ratio(a: dict[str, Any], b: dict[str, Any]) -> float | None:
    """``a``'s median over ``b``'s, 3 decimals (None when either has no samples)."""
    if not a.get("median_us") or not b.get("median_us"):
        return None
    return round(float(a["median_us"]) / float(b["median_us"]), 3)
