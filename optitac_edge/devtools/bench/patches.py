"""Several fiber patches on one camera: every patch's pipeline on the same frame (issue 16).

Patches of the default 217-fiber array in a grid on one camera frame
(:class:`~optitac_edge.sim.patches.PatchFrames`), each calibrated on its crop
and placed in the frame (:func:`~optitac_edge.calibration.region.place_bundle`). One
patch at a time is pressed (a 5 mm circle at a new place every frame), the
others rest, as a hand holding an object; every third frame a second patch is
pressed too (a grasp between two fingers: two contacts on two patches). A camera frame's time is all its
patches' pipelines, back to back and paced at the camera's rate
(:func:`~optitac_edge.devtools.bench.paced.run_interleaved`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

from optitac_edge.core.pipeline import Pipeline
from optitac_edge.devtools.bench.paced import Paced, run_interleaved

if TYPE_CHECKING:
    from optitac_edge.calibration.region import Region

#: Distinct frames the patches' presses cycle through.
PATCH_FRAMES = 120
#: Pixels between neighbouring patches.
GAP_PX = 8


def patch_regions(n_patches: int, width: int, height: int) -> list[Region]:
    """The patches' regions: a grid of ``n_patches`` on a ``width`` x ``height`` frame, :data:`GAP_PX` apart."""
    from optitac_edge.calibration.region import Region

    cols = math.ceil(math.sqrt(n_patches))
    rows = math.ceil(n_patches / cols)
    w, h = width // cols, height // rows
    return [Region((k % cols) * w, (k // cols) * h, w - GAP_PX, h - GAP_PX) for k in range(n_patches)]


def patch_pipelines(n_patches: int, width: int, height: int, seed: int = 1
                    ) -> tuple[list[Pipeline], list[np.ndarray], list[np.ndarray]]:
    """``n_patches`` placed pipelines on one ``width`` x ``height`` camera, its rest frames and press frames."""
    from optitac_edge.calibration.fibers import calibrate_fibers
    from optitac_edge.calibration.region import place_bundle
    from optitac_edge.sim.patches import PatchFrames, crop
    from optitac_edge.sim.skin import Indenter

    regions = patch_regions(n_patches, width, height)
    cam = PatchFrames(regions, width, height, seed=seed)
    rest = [cam.frame() for _ in range(10)]
    stacked = np.stack(rest)
    pipes = [Pipeline(place_bundle(calibrate_fibers(crop(stacked, r), "gray"), r, width, height))
             for r in regions]
    rng = np.random.default_rng(seed + 1)
    frames = []
    for i in range(PATCH_FRAMES):
        press = Indenter("circle", float(rng.uniform(-4, 4)), float(rng.uniform(-4, 4)), 0.0, 5.0, 3.0)
        pressed = {i % n_patches} | ({(i + 1) % n_patches} if i % 3 == 2 else set())  # a grasp: two patches
        frames.append(cam.frame([(press,) if k in pressed else () for k in range(n_patches)]))
    return pipes, rest, frames


def measure_patches(n_patches: int, width: int, height: int, fps: float, n_frames: int) -> dict[str, Any]:
    """Per camera frame (all patches), back to back and paced at ``fps``: medians and p99, µs."""
    pipes, rest, frames = patch_pipelines(n_patches, width, height)

    def process(frame: np.ndarray, t_ns: int) -> int:
        return sum(p.process_recorded(frame, t_ns).n_contacts for p in pipes)

    out: dict[str, Any] = {"patches": n_patches, "frame_size": [width, height],
                           "fibers_per_patch": pipes[0].bundle.layout.n_fibers}
    for mode, rate in (("back_to_back", 0.0), ("paced", fps)):
        for p in pipes:
            p.reset_baseline()
        res = run_interleaved([Paced("frame", process, rest + frames, len(rest), count=int)], rate, n_frames,
                              warmup_per_config=min(100, n_frames))
        out[mode] = res["frame"]
    return out
