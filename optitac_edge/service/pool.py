"""A camera's sensors on several cores: their pipelines run side by side, their messages go out in order.

The compiled kernel releases the GIL for a frame's work (:mod:`optitac_edge.core.compiled`),
so the pipelines of the sensors one camera reads (a hand's patches) can run at
once on a board's spare cores. :class:`SensorPool` keeps a few worker threads for
the life of the service; per frame the loop hands each worker a share of the
sensors, processes its own share, and waits for the rest. Everything after the
pipelines (counts, the network, the messages to the MCU) stays on the loop's
thread, in the sensors' order: the MCU hears exactly what a single thread would
send.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence

from optitac_edge.io.threads import NamedThread

#: Cores kept free of sensor work: the camera's and the link's threads, the loop's own.
RESERVED_CORES = 2


def spare_workers(n_sensors: int, cores: int | None = None) -> int:
    """Worker threads worth starting for ``n_sensors`` sensors on a board with ``cores`` cores (default: this
    one's, as the process may use them): one per sensor beyond the loop's own, as many as the cores beyond
    :data:`RESERVED_CORES` (0 on a board with two cores or fewer, or one sensor)."""
    if cores is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(0, min(n_sensors - 1, cores - RESERVED_CORES))


class _Worker:
    """One thread running the jobs it is handed, one batch per frame."""

    def __init__(self, name: str) -> None:
        self.jobs: Sequence[Callable[[], object]] = ()
        self.results: list[object] = []
        self.go = threading.Event()
        self.done = threading.Event()
        self.stopping = False
        self.thread = NamedThread(target=self._run, name=name, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while True:
            self.go.wait()
            self.go.clear()
            if self.stopping:
                return
            results = self.results
            results.clear()
            for job in self.jobs:
                try:
                    results.append(job())
                except Exception as exc:  # noqa: BLE001 - handed back to the loop, which counts it
                    results.append(exc)
            self.done.set()


class SensorPool:
    """Runs one frame's jobs (one per sensor) on the loop's thread and ``workers`` others.

    Parameters
    ----------
    workers : int
        Worker threads (0: everything on the calling thread, nothing started).

    Notes
    -----
    :meth:`run` returns each job's return value, or the exception it raised, in
    the jobs' order. Jobs are dealt round-robin: the caller's thread takes jobs
    0, w + 1, ..., worker ``i`` jobs i + 1, ... Close with :meth:`close` (idempotent).
    """

    def __init__(self, workers: int) -> None:
        self._workers = [_Worker(f"optitac-sensors-{i + 1}") for i in range(max(0, workers))]
        self._own: list[Callable[[], object]] = []
        self._shares: list[list[Callable[[], object]]] = [[] for _ in self._workers]

    @property
    def workers(self) -> int:
        return len(self._workers)

    def run(self, jobs: Sequence[Callable[[], object]]) -> list[object]:
        """Every job's result (or exception), in order."""
        if not self._workers or len(jobs) < 2:
            return [_call(job) for job in jobs]
        stride = len(self._workers) + 1
        own = self._own
        own[:] = jobs[::stride]
        busy = []
        for i, worker in enumerate(self._workers):
            share = self._shares[i]
            share[:] = jobs[i + 1::stride]
            if share:
                worker.jobs = share
                worker.done.clear()
                worker.go.set()
                busy.append(worker)
        mine = [_call(job) for job in own]
        for worker in busy:
            worker.done.wait()
        out: list[object] = [None] * len(jobs)
        out[::stride] = mine
        for i, worker in enumerate(self._workers):
            if self._shares[i]:
                out[i + 1::stride] = worker.results
        return out

    def close(self) -> None:
        """Stop the worker threads (idempotent)."""
        for worker in self._workers:
            worker.stopping = True
            worker.go.set()
        for worker in self._workers:
            worker.thread.join(timeout=5.0)
        self._workers = []


def _call(job: Callable[[], object]) -> object:
    try:
        return job()
    except Exception as exc:  # noqa: BLE001 - handed back to the loop, which counts it
        return exc
