"""The bench's inputs: the machine, a bundle and frames (the simulated camera's, or a recording's)."""

from __future__ import annotations

import os
import platform
from pathlib import Path
from typing import Any

import numpy as np


def machine() -> dict[str, Any]:
    """The machine the bench ran on."""
    cpu = platform.processor() or platform.machine()
    try:
        info = dict(line.split(":", 1) for line in Path("/proc/cpuinfo").read_text().splitlines()
                    if ":" in line)
        info = {k.strip().lower(): v.strip() for k, v in info.items()}
        cpu = info.get("model name") or info.get("hardware") or info.get("model") or cpu
    except OSError:
        pass
    import cv2

    return {"cpu": cpu, "cores": os.cpu_count(), "machine": platform.machine(),
            "python": platform.python_version(), "numpy": np.__version__, "opencv": cv2.__version__,
            "os": platform.platform(), "blas_threads_env": os.environ.get("OPENBLAS_NUM_THREADS"),
            "load_average_at_start": [round(v, 2) for v in os.getloadavg()]}


def sim_frames(n: int, rgb: bool, fps: float, rest: int, seed: int = 7) -> list[np.ndarray]:
    """``n`` frames of the live simulated camera (``rest`` contact-free, then random presses)."""
    from optitac_edge.sim.camera import SimCamera

    cam = SimCamera(fps=fps, rgb=rgb, seed=seed, rest_frames=rest, realtime=False)
    frames = []
    for _ in range(n):
        captured = cam.read()
        assert captured is not None
        frames.append(np.ascontiguousarray(captured.frame).copy())
    cam.close()
    return frames


def load_inputs(source: str, cal: Path | None, rgb: bool, workdir: Path, n_unique: int,
                fps: float) -> tuple[Any, Path, list[np.ndarray], str]:
    """(bundle, bundle path, frames, description)."""
    from optitac_edge.io.bundle_file import load_bundle, save_bundle

    if source == "sim":
        from optitac_edge.sim.bundles import cached_sim_bundle

        path = cal if cal is not None else cached_sim_bundle(workdir, rgb=rgb)
        bundle = load_bundle(path)
        rest = max(int(bundle.baseline_frames), 10)
        frames = sim_frames(n_unique, bundle.fibers.pixel_format == "rgb", fps, rest)
        return bundle, path, frames, f"simulated camera, {len(frames)} distinct frames"
    from optitac_edge.io.recording import Recording

    rec = Recording(source)
    frames = [np.ascontiguousarray(f) for f in rec]
    if cal is None:
        from optitac_edge.calibration.fibers import calibrate_fibers

        bundle = calibrate_fibers(rec.rest_frames(), rec.pixel_format)
        workdir.mkdir(parents=True, exist_ok=True)
        path = workdir / "cal-recording.npz"
        bundle = save_bundle(bundle, path)
    else:
        path = cal
        bundle = load_bundle(cal)
    return bundle, path, frames, f"recording {source}, {len(frames)} frames"
