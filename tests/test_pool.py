"""The sensors' worker pool: results in order, failures handed back, jobs side by side, threads stopped."""

from __future__ import annotations

import threading

import pytest

from optitac_edge.service.pool import RESERVED_CORES, SensorPool, spare_workers


@pytest.mark.parametrize(("sensors", "cores", "workers"), [(1, 8, 0), (6, 2, 0), (6, 3, 1), (6, 4, 2),
                                                          (2, 8, 1), (6, 16, 5)])
def test_spare_workers_leave_the_reserved_cores_free(sensors, cores, workers) -> None:
    assert RESERVED_CORES == 2
    assert spare_workers(sensors, cores) == workers


@pytest.mark.parametrize("workers", [0, 1, 3])
def test_results_come_back_in_the_jobs_order_with_failures_as_values(workers) -> None:
    pool = SensorPool(workers)
    try:
        for n in (0, 1, 2, 5, 7):
            def job(i: int) -> int:
                if i == 3:
                    raise ValueError("sensor 3 failed")
                return i * i

            got = pool.run([lambda i=i: job(i) for i in range(n)])
            assert [g if not isinstance(g, Exception) else str(g) for g in got] == \
                [i * i if i != 3 else "sensor 3 failed" for i in range(n)]
    finally:
        pool.close()


def test_the_jobs_of_a_frame_run_side_by_side() -> None:
    """Three jobs that each wait for the other two: they finish only if they run at once."""
    pool = SensorPool(2)
    barrier = threading.Barrier(3, timeout=10.0)
    names = []

    def job() -> int:
        names.append(threading.current_thread().name)
        return barrier.wait()

    try:
        got = pool.run([job, job, job])
        assert sorted(got) == [0, 1, 2]  # type: ignore[type-var]
        assert len(set(names)) == 3 and threading.current_thread().name in names
    finally:
        pool.close()


def test_close_stops_the_threads_and_is_idempotent() -> None:
    pool = SensorPool(2)
    threads = [w.thread for w in pool._workers]
    pool.close()
    pool.close()
    assert not any(t.is_alive() for t in threads) and pool.workers == 0
    assert pool.run([lambda: 1, lambda: 2]) == [1, 2]  # on the caller's thread
