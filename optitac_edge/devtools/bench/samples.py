"""Timing samples: preallocated buffers, their summary (median, p99, max), the process's RSS."""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np


def summary(samples_ns: list[int] | np.ndarray) -> dict[str, Any]:
    a = np.asarray(samples_ns, dtype=np.float64) / 1e3
    if a.size == 0:
        return {"n": 0, "median_us": None, "p99_us": None, "max_us": None}
    return {"n": int(a.size), "median_us": round(float(np.median(a)), 2),
            "p99_us": round(float(np.percentile(a, 99)), 2), "max_us": round(float(a.max()), 2)}


def rss_bytes() -> int:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):  # not Linux
        import resource

        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def timed(fn: Any, *args: Any) -> int:
    t0 = time.perf_counter_ns()
    fn(*args)
    return time.perf_counter_ns() - t0


class Samples:
    """A preallocated int64 sample buffer with ``append``."""

    def __init__(self, n: int) -> None:
        self._a = np.empty(n, dtype=np.int64)
        self._a.fill(0)  # touch every page now: np.zeros' lazily mapped pages would grow the RSS
        self.n = 0

    def append(self, v: int) -> None:
        if self.n < self._a.size:
            self._a[self.n] = v
            self.n += 1

    @property
    def values(self) -> np.ndarray:
        return self._a[:self.n]
