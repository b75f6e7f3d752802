"""Shared fixtures: small simulated recordings and bundles, made once per session."""

from __future__ import annotations

import os

# Before numpy is imported, here and in every pytest-xdist worker (they inherit this environment): one BLAS
# thread a process. The suite runs one worker a core, and OpenBLAS's own threads a worker then only fight the
# other worker for the cores (measured on 2 cores: five calibration-heavy files 100-122 s with OpenBLAS's
# default, 78-90 s with one thread, three pairs). The tests' subprocesses inherit it too. A user's process is
# not affected.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import importlib.util
import sys
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest
from hypothesis import settings as hypothesis_settings

# Generated inputs (hypothesis) the same on every run and machine: a suite that passed passes again; a new case is
# found by raising a test's max_examples (or HYPOTHESIS_PROFILE=random), not by chance in CI.
hypothesis_settings.register_profile("deterministic", derandomize=True, database=None, print_blob=True)
hypothesis_settings.register_profile("random", database=None, print_blob=True)
hypothesis_settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "deterministic"))

from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.io.bundle_file import save_bundle
from optitac_edge.io.recording import Recording
from optitac_edge.sim.scenarios import write_scenario

#: ``path::function`` of the tests the quick tier leaves out (tests/slow_tests.txt: measured, see its header).
SLOW_TESTS = frozenset(line.strip() for line in (Path(__file__).parent / "slow_tests.txt").read_text().splitlines()
                       if line.strip() and not line.startswith("#"))


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark the tests of tests/slow_tests.txt slow (``pytest -m "not slow"``: the quick tier); a listed name
    that no collected test has is an error when the whole suite is collected (the list must not rot)."""
    seen = set()
    for item in items:
        name = item.nodeid.split("[")[0].removeprefix("tests/")
        for listed in (name, name.split("::")[0]):
            if listed in SLOW_TESTS:
                item.add_marker(pytest.mark.slow)
                seen.add(listed)
    whole = len(items) > 1500 and not config.option.keyword and not config.option.markexpr  # the whole suite
    missing = SLOW_TESTS - seen
    if whole and missing:
        raise pytest.UsageError(f"tests/slow_tests.txt names tests that do not exist: {', '.join(sorted(missing)[:5])}")


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto`` (pyproject's addopts): one worker a core, and one more.

    Many tests wait in real time (a serial pty at 120 fps, a soak's subprocess, the rig's ptys, a browser), and a
    worker that waits leaves its core idle; the extra worker runs a calculation meanwhile. Measured on 2 cores, the
    whole suite: 2 workers 234.5 s (1 734 tests), 3 workers 211.1 s, 4 workers 223.9 s (more workers build their
    module fixtures again).
    """
    return len(os.sched_getaffinity(0)) + 1


@pytest.fixture(scope="session")
def sim_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("sim")


@pytest.fixture(scope="session")
def unseen_rec(sim_dir) -> Path:
    return write_scenario(sim_dir / "unseen", "unseen", seed=1)


@pytest.fixture(scope="session")
def rest_rec(sim_dir) -> Path:
    return write_scenario(sim_dir / "rest", "rest", seed=2)


@pytest.fixture(scope="session")
def bundle_path(sim_dir, rest_rec) -> Path:
    """The fiber map of the rest recording (no calibration models), as ``calibrate fibers`` writes it."""
    rec = Recording(rest_rec)
    path = sim_dir / "cal.npz"
    save_bundle(calibrate_fibers(rec.rest_frames(), rec.pixel_format), path)
    return path


#: Where the measured code allocates: the package and the tests (numpy's and OpenCV's C allocations are
#: traced to the Python line that called them). pytest-xdist's own thread allocates while a test runs
#: (the next tests arriving from the controller): its lines are not counted.
_OURS = (tracemalloc.Filter(True, "*/optitac_edge/*"), tracemalloc.Filter(True, "*/tests/*"),
         tracemalloc.Filter(False, __file__))  # the measuring itself (the snapshots)


def _traced_bytes(fn: Callable[[], object], calls: int, warmup: int = 10) -> tuple[int, int]:
    """(net bytes still allocated by our code after ``calls`` calls of ``fn``, largest transient above the
    start).

    tracemalloc's peak counts every thread's allocations (pytest-xdist's too), so the calls are made in
    three rounds and the smallest round's peak is the code's: another thread can only add to it.
    """
    for _ in range(warmup):
        fn()
    tracemalloc.start()
    try:
        # a few calls traced before counting: an object made before tracing and replaced by a
        # call (a new int stored in an attribute) would count its replacement but not its free
        for _ in range(3):
            fn()
        before = tracemalloc.take_snapshot().filter_traces(_OURS)
        peaks = []
        for _ in range(3):
            start = tracemalloc.get_traced_memory()[0]
            tracemalloc.reset_peak()
            for _ in range(calls):
                fn()
            peaks.append(tracemalloc.get_traced_memory()[1] - start)
        after = tracemalloc.take_snapshot().filter_traces(_OURS)
    finally:
        tracemalloc.stop()
    net = sum(stat.size_diff for stat in after.compare_to(before, "filename"))
    return net, min(peaks)


@pytest.fixture
def traced_bytes() -> Callable[..., tuple[int, int]]:
    """``traced_bytes(fn, calls)``: tracemalloc's net and peak bytes over ``calls`` calls of ``fn``."""
    return _traced_bytes


def load_tool(name: str) -> ModuleType:
    """``tools/NAME.py``, imported from its file (the tools are scripts, not a package)."""
    path = Path(__file__).resolve().parents[1] / "tools" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # as an import does (a dataclass of the tool looks its module up there)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="session")
def fuzz_tool() -> ModuleType:
    """``tools/fuzz_decoder.py`` (the decoder's independent oracle)."""
    return load_tool("fuzz_decoder")


@pytest.fixture(scope="session")
def aarch64_tool() -> ModuleType:
    """``tools/kernel_aarch64.py`` (the compiled kernel replayed on another architecture)."""
    return load_tool("kernel_aarch64")


@pytest.fixture(scope="session")
def roundtrip_tool() -> ModuleType:
    """``tools/lerobot_roundtrip.py`` (a LeRobot dataset compared with the contacts CSVs)."""
    return load_tool("lerobot_roundtrip")
