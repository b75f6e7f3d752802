"""Frames of the simulated sensor at 240 fps: rest, a 5 mm circle held still, then slid along +x (tests of
contact motion on every interface)."""

from __future__ import annotations

import numpy as np

from optitac_edge.sim.sensor import SimulatedSensor
from optitac_edge.sim.skin import Indenter

FPS = 240.0


def slide_frames(rest: int, held: int, slid: int, speed_mm_s: float, *, seed: int, x0_mm: float = -3.0,
                 y_mm: float = 0.5) -> list[np.ndarray]:
    """``rest`` contact-free frames, ``held`` frames pressed at (``x0_mm``, ``y_mm``) 2.5 mm deep, then ``slid``
    frames moving along +x at ``speed_mm_s`` (the first one frame period along)."""
    sensor = SimulatedSensor(fps=FPS, seed=seed)
    xs = [None] * rest + [x0_mm] * held + [x0_mm + speed_mm_s * (k + 1) / FPS for k in range(slid)]
    return [sensor.frame(() if x is None else (Indenter("circle", x, y_mm, size_mm=5.0, depth_mm=2.5),))
            for x in xs]
