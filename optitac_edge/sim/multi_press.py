"""Several indenters pressed at once: frames with a fixed number of simultaneous contacts.

The bench times the per-frame loop with 0, 1, 2 and 4 contacts in every
frame (a hand closing on an object presses several sites of one skin). The
sites sit on a ring at half the array's radius, evenly spaced (one site:
the ring's first point), far enough apart that each is its own contact;
every indenter stays pressed (its depth breathes between 60 % and 100 %
of its full depth) and its shape, size and angle change from press to press.
"""

from __future__ import annotations

import math

import numpy as np

from optitac_edge.core.layout import FiberLayout
from optitac_edge.sim.optics import CameraOptics
from optitac_edge.sim.sensor import SimulatedSensor
from optitac_edge.sim.skin import Indenter

#: Shapes and full sizes (mm) the indenters cycle through: small enough that 4 stay apart.
SHAPES: tuple[tuple[str, float], ...] = (("circle", 4.0), ("square", 3.5), ("ellipse", 5.0), ("triangle", 4.5))
#: The sites' ring, as a fraction of the array's radius.
RING = 0.55
#: Frames each press lasts before the next shape takes the site.
PRESS_FRAMES = 48


def press_sites(n_contacts: int, radius_mm: float) -> list[tuple[float, float]]:
    """``n_contacts`` (x, y) sites, mm, evenly spaced on a ring at ``RING * radius_mm``."""
    r = RING * radius_mm
    return [(r * math.cos(2 * math.pi * k / n_contacts + 0.3), r * math.sin(2 * math.pi * k / n_contacts + 0.3))
            for k in range(n_contacts)]


def multi_press_indenters(n_contacts: int, frame: int, radius_mm: float, seed: int = 0) -> list[Indenter]:
    """The ``n_contacts`` indenters pressed at ``frame`` (a pure function of its arguments)."""
    press, t = divmod(frame, PRESS_FRAMES)
    depth_frac = 0.8 + 0.2 * math.cos(2 * math.pi * t / PRESS_FRAMES)
    out = []
    for k, (x, y) in enumerate(press_sites(n_contacts, radius_mm)):
        rng = np.random.default_rng([seed, press, k])
        shape, size = SHAPES[(press + k) % len(SHAPES)]
        out.append(Indenter(shape=shape, x_mm=x + float(rng.uniform(-0.5, 0.5)),
                            y_mm=y + float(rng.uniform(-0.5, 0.5)), angle_deg=float(rng.uniform(-90, 90)),
                            size_mm=size * float(rng.uniform(0.9, 1.1)),
                            depth_mm=float(rng.uniform(2.5, 3.0)) * depth_frac))
    return out


def multi_press_frames(n_contacts: int, n_frames: int, rest_frames: int, *, layout: FiberLayout | None = None,
                       rgb: bool = False, fps: float = 240.0, seed: int = 0) -> list[np.ndarray]:
    """Rendered frames: ``rest_frames`` contact-free, then ``n_frames`` with ``n_contacts`` pressed throughout.

    Parameters
    ----------
    n_contacts : int
        Indenters pressed at once (0: rest frames only, with the camera's noise).
    n_frames, rest_frames : int
        Frames with the indenters, and contact-free frames before them.
    layout : FiberLayout, optional
        The sensor's layout (default: the 217-fiber array); the array fills
        the frame the same way whatever its fiber count.
    rgb : bool
        (H, W, 3) frames instead of gray.
    fps, seed : float, int
        Frame rate of the sensor's clock, and the seed of the noise and of the presses.

    Returns
    -------
    list of ndarray, uint8
        ``rest_frames + n_frames`` frames, 640 x 480.
    """
    if n_contacts < 0 or n_frames < 0 or rest_frames < 0:
        raise ValueError("n_contacts, n_frames and rest_frames must be >= 0")
    sensor = SimulatedSensor(layout=layout, optics=CameraOptics(rgb=rgb), seed=seed, fps=fps)
    radius = sensor.layout.radius_mm
    frames = [sensor.frame(()) for _ in range(rest_frames)]
    frames += [sensor.frame(multi_press_indenters(n_contacts, i, radius, seed)) for i in range(n_frames)]
    return frames
