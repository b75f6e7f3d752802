"""One Pipeline serves one thread: a frame from a second thread meanwhile is refused in one clear error, never
a crash (issue 41: two threads on one pipeline segfaulted in 3 of 4 runs, or hung)."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from optitac_edge.core.pipeline import Pipeline
from optitac_edge.errors import PipelineBusy
from optitac_edge.io.bundle_file import load_bundle
from optitac_edge.sim.camera import SimCamera

TOOLS = Path(__file__).resolve().parents[1] / "tools"


def _frames(n: int) -> list[np.ndarray]:
    cam = SimCamera(fps=240, seed=3, rest_frames=12, realtime=False)
    try:
        return [np.array(cam.read().frame) for _ in range(n)]  # type: ignore[union-attr]
    finally:
        cam.close()


@pytest.mark.parametrize("compiled", [False, True])
def test_a_frame_from_a_second_thread_is_refused_while_one_runs(bundle_path, compiled, monkeypatch) -> None:
    pipe = Pipeline(load_bundle(bundle_path), compiled=compiled)
    if compiled and not pipe.compiled:
        pytest.skip("the kernel is not built here")
    frames = _frames(16)
    for k, f in enumerate(frames[:12]):
        pipe.process(f, k * 1000)
    inside, leave = threading.Event(), threading.Event()
    run = pipe.engine.run

    def held_run(*args: object) -> int:  # the first thread's frame stays in the pipeline until told
        inside.set()
        leave.wait(10)
        return run(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(pipe.engine, "run", held_run)
    results: list[object] = []
    first = threading.Thread(target=lambda: results.append(pipe.process(frames[12], 12_000)))
    first.start()
    assert inside.wait(10)
    with pytest.raises(PipelineBusy, match="another thread"):
        pipe.process(frames[13], 13_000)
    with pytest.raises(PipelineBusy):
        pipe.process_recorded(frames[13], 13_000)
    leave.set()
    first.join(10)
    assert len(results) == 1 and results[0] is pipe.result and pipe.result.t_ns == 12_000  # the refused frame changed nothing
    monkeypatch.undo()
    assert pipe.process(frames[14], 14_000).t_ns == 14_000  # and the pipeline goes on


def test_two_threads_on_one_pipeline_and_its_kernel_never_crash(tmp_path, bundle_path) -> None:
    """The tool's run: both threads through process(), one of them also straight into the compiled kernel
    (past the pipeline's guard): every call returned or was refused, and the process exited normally."""
    from optitac_edge.devtools.bench.scaling import contact_frames

    frames = tmp_path / "four.npy"
    np.save(frames, np.stack(contact_frames(4, False, 240.0)))
    proc = subprocess.run([sys.executable, str(TOOLS / "two_threads.py"), "--worker", str(bundle_path), str(frames),
                           "200"], capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    counts = json.loads(proc.stdout)
    assert counts["other"] == 0 and counts["returned"] + counts["refused"] == 400 and counts["returned"] > 0
