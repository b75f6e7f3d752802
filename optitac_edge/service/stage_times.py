"""The frame loop's own CPU time by stage, kept when asked (``optitac-edge run --stage-times FILE``).

Two stages of every processed camera frame, on the loop's thread: the sensors' pipelines
(:meth:`Pipeline.process <optitac_edge.core.pipeline.Pipeline.process>`, on the pool's workers where
there are some: then the loop's wait for them) and the send path (counters, the network's copy, the
outbox's messages packed and handed to the transport). Each is a thread-CPU clock difference, kept per
frame in a buffer allocated once; nothing is logged per frame. docs/performance.md's harness
(``tools/pace_run.py``) reads the file.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

#: Frames kept (the last ones; about 4.5 minutes at 240 fps).
CAPACITY = 1 << 16


class StageTimes:
    """Per-frame CPU of the loop's stages, ns.

    Parameters
    ----------
    clock : callable, optional
        The loop thread's CPU clock, ns (default :func:`time.thread_time_ns`).
    capacity : int
        Frames kept; later frames overwrite the oldest.
    """

    STAGES = ("pipeline", "send")

    def __init__(self, clock: Callable[[], int] = time.thread_time_ns, capacity: int = CAPACITY) -> None:
        self.clock = clock
        self._ns = np.zeros((capacity, len(self.STAGES)), np.int64)
        self.frames = 0

    def add(self, pipeline_ns: int, send_ns: int) -> None:
        """One frame's two stages."""
        row = self._ns[self.frames % len(self._ns)]
        row[0] = pipeline_ns
        row[1] = send_ns
        self.frames += 1

    def summary(self, skip: int = 0) -> dict[str, Any]:
        """Median, mean and 99th percentile of each stage, µs, over the kept frames after the first ``skip``."""
        kept = self._ns[:min(self.frames, len(self._ns))]
        if self.frames <= len(self._ns):
            kept = kept[skip:]
        out: dict[str, Any] = {"frames": len(kept)}
        for k, name in enumerate(self.STAGES):
            col = kept[:, k] / 1e3
            out[name] = ({"median_us": round(float(np.median(col)), 2), "mean_us": round(float(col.mean()), 2),
                          "p99_us": round(float(np.percentile(col, 99)), 2)} if len(col) else None)
        return out
