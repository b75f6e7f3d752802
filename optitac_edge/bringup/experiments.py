"""The paper's experiments as lists of presses for an indentation rig (sensor frame, pure functions).

``seen``    5 mm circle, 3 mm deep, over every fiber.
``unseen``  5 mm circle, 3 mm deep, in 0.25 mm steps along x (y = 0), then y
            (x = 0), as far as it stays 0.5 mm inside the array
            (:func:`~optitac_edge.core.reach.unseen_line`).
``repeat``  5 mm circle, 3 mm deep, 10 presses at each of 5 points (the centre and
            half the radius out at 45, 135, 225, 315 degrees).
``widths``  circles of ``WIDTHS_MM``, 3 mm deep, 5 presses each at random positions
            fully on the array; one block per indenter (the operator changes it).
``shapes``  5 shapes (the circle first), each in 4 blocks of angles across its symmetry period, 10
            presses a block at random positions fully on the array, 3 mm deep.
``depths``  a 5 mm circle at the centre and 6 points half the radius out (on an array wider than the
            paper's, 6 more as far out as ``unseen`` presses go:
            :func:`~optitac_edge.core.reach.depth_points`), at ``DEPTHS_MM``, twice each, in random
            order (for depth calibration).
``slide``   a 5 mm circle pressed 2.5 mm deep, held, then slid in the skin through the centre at each of
            ``SLIDE_SPEEDS_MM_S`` (capped at the rig's feed limit), held again and lifted (contact motion:
            ``evaluate``'s motion metrics; truth.csv gets the motion columns from the rig's pose).
``vibrate`` a 5 mm circle pressed 2.5 mm deep, held, shaken by 0.05 mm at each of ``VIBRATE_HZ`` along the
            rig's x, y and z, held quiet and lifted (a rig that can shake: ``sim://``).

Presses are grouped by indenter so the operator changes it once per block. The sizes and steps above are the
paper's, for its 1.5 mm array; on an array of another pitch every indenter size, step and lateral margin scales
with the pitch (:func:`~optitac_edge.core.layout.scaled_mm`: a 61-fiber array at 4 mm is pressed with a 13.35 mm
circle in 0.65 mm steps), the depths stay as they are (the skin's, in mm).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from optitac_edge.core.layout import FiberLayout, pitch_scale, scaled_mm
from optitac_edge.core.reach import depth_points, unseen_line

EXPERIMENTS = ("seen", "unseen", "repeat", "widths", "shapes", "depths", "slide", "vibrate")
#: ``vibrate``: the frequencies, Hz, each along the rig's x, y and z, and the amplitude, mm.
VIBRATE_HZ: tuple[float, ...] = (30.0, 45.0, 60.0, 80.0, 100.0)
VIBRATE_AMPLITUDE_MM = 0.05
#: ``slide``: the speeds, mm/s (each capped at the rig's feed limit) and their directions in the sensor frame, deg.
SLIDE_SPEEDS_MM_S: tuple[float, ...] = (2.0, 5.0, 10.0, 20.0, 50.0, 100.0)
SLIDE_DIRECTIONS_DEG: tuple[float, ...] = (0.0, 72.0, 144.0, 216.0, 288.0, 36.0)
WIDTHS_MM: tuple[float, ...] = (2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0, 14.0, 16.0)
DEPTHS_MM: tuple[float, ...] = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0)
#: The circle first: the collection's registration presses use the experiment's first circle.
SHAPE_SIZE_MM = {"circle": 6.0, "edge": 1.5, "square": 6.0, "ellipse": 7.0, "triangle": 7.0}
ANGLE_PERIOD_DEG = {"circle": 0.0, "square": 90.0, "triangle": 120.0, "ellipse": 180.0, "edge": 180.0}
#: How far an indenter's outline reaches beyond its size/2 (edge: its length), mm.
EDGE_LENGTH_MM = 12.0


@dataclass(frozen=True)
class PlannedPress:
    """One press of an experiment.

    Attributes
    ----------
    x_mm, y_mm : float
        Centre of the press in the sensor frame, mm.
    depth_mm : float
        Indentation depth below the skin's surface, mm.
    shape : str
    size_mm : float
        Diameter of a circle, side of a square or triangle, major axis of an ellipse, width of an edge.
    angle_deg : float
        The indenter's angle as mounted, counter-clockwise from the rig's +X, degrees.
    slide_x_mm, slide_y_mm, slide_mm_s : float
        ``slide``: after the hold the tip slides in the skin to this point (sensor frame) at this speed
        (0: no slide).
    shake_axis, shake_hz : str, float
        ``vibrate``: after the hold the rig shakes the tip along its ``x``, ``y`` or ``z`` by
        :data:`VIBRATE_AMPLITUDE_MM` at this frequency (0: no shake).
    """

    x_mm: float
    y_mm: float
    depth_mm: float
    shape: str = "circle"
    size_mm: float = 5.0
    angle_deg: float = 0.0
    slide_x_mm: float = 0.0
    slide_y_mm: float = 0.0
    slide_mm_s: float = 0.0
    shake_axis: str = ""
    shake_hz: float = 0.0

    @property
    def indenter(self) -> str:
        """Label of the indenter this press needs (``shape:size@angle``)."""
        return f"{self.shape}:{self.size_mm:g}@{self.angle_deg:g}"


def inscribed_radius(layout: FiberLayout) -> float:
    """Radius (mm) of the largest origin-centred circle inside the fiber centres' convex hull."""
    from scipy.spatial import ConvexHull

    return float(-ConvexHull(layout.xy_mm).equations[:, 2].max())


def _reach(shape: str, size: float, scale: float) -> float:
    if shape == "edge":
        return scaled_mm(EDGE_LENGTH_MM, scale) / 2.0
    if shape == "ellipse" or shape == "triangle":
        return size / 2.0 if shape == "ellipse" else size / math.sqrt(3.0)
    return size / 2.0 * (math.sqrt(2.0) if shape == "square" else 1.0)


def _random_on_array(rng: np.random.Generator, layout: FiberLayout, shape: str, size: float) -> tuple[float, float]:
    room = inscribed_radius(layout) - _reach(shape, size, pitch_scale(layout))
    if room < inscribed_radius(layout) / 4:
        return 0.0, 0.0
    r, t = room * math.sqrt(rng.uniform()), rng.uniform(0.0, 2 * math.pi)
    return r * math.cos(t), r * math.sin(t)


def spread(presses: list[PlannedPress], limit: int | None) -> list[PlannedPress]:
    """``limit`` presses spread evenly over the experiment, in its order (all of them without a limit).

    The first N would hold only the experiment's first block (``shapes``: only edges; ``unseen``: only
    the x axis).
    """
    if limit is None or limit >= len(presses):
        return list(presses)
    picks = np.unique(np.round(np.linspace(0, len(presses) - 1, max(limit, 1))).astype(int))
    return [presses[int(k)] for k in picks]


def plan(experiment: str, layout: FiberLayout, seed: int = 0) -> list[PlannedPress]:
    """The presses of ``experiment`` (one of :data:`EXPERIMENTS`) on ``layout``, grouped by indenter.

    Raises
    ------
    ValueError
        For an unknown experiment.
    """
    rng = np.random.default_rng(seed)
    k = pitch_scale(layout)
    circle = scaled_mm(5.0, k)
    if experiment == "seen":
        return [PlannedPress(float(x), float(y), 3.0, size_mm=circle) for x, y in layout.xy_mm]
    if experiment == "unseen":
        step = scaled_mm(0.25, k)
        x_line, y_line = (unseen_line(layout, axis, circle, step, k) for axis in (0, 1))
        return ([PlannedPress(float(v), 0.0, 3.0, size_mm=circle) for v in x_line]
                + [PlannedPress(0.0, float(v), 3.0, size_mm=circle) for v in y_line])
    if experiment == "repeat":
        ring = 0.5 * layout.radius_mm
        points = [(0.0, 0.0)] + [(ring * math.cos(math.radians(a)), ring * math.sin(math.radians(a)))
                                 for a in (45.0, 135.0, 225.0, 315.0)]
        return [PlannedPress(x, y, 3.0, size_mm=circle) for x, y in points for _ in range(10)]
    if experiment == "widths":
        widths = [scaled_mm(d, k) for d in WIDTHS_MM]
        return [PlannedPress(*_random_on_array(rng, layout, "circle", d), 3.0, "circle", d)
                for d in widths for _ in range(5)]
    if experiment == "shapes":
        out = []
        for shape, size_mm in SHAPE_SIZE_MM.items():
            size = scaled_mm(size_mm, k)
            period = ANGLE_PERIOD_DEG[shape]
            angles = [0.0] if not period else [period * a / 4 for a in range(4)]
            per_block = 40 // len(angles)
            for angle in angles:
                out += [PlannedPress(*_random_on_array(rng, layout, shape, size), 3.0, shape, size, angle)
                        for _ in range(per_block)]
        return out
    if experiment == "slide":  # through the centre, up to 8 mm, in a straight line at each speed
        out = []
        for i, speed in enumerate(SLIDE_SPEEDS_MM_S):
            theta = math.radians(SLIDE_DIRECTIONS_DEG[i % len(SLIDE_DIRECTIONS_DEG)])
            half = min(max(speed, 2.0), scaled_mm(8.0, k), layout.radius_mm - scaled_mm(4.0, k)) / 2
            ux, uy = math.cos(theta), math.sin(theta)
            out.append(PlannedPress(-half * ux, -half * uy, 2.5, size_mm=circle, slide_x_mm=half * ux,
                                    slide_y_mm=half * uy, slide_mm_s=speed))
        return out
    if experiment == "vibrate":
        return [PlannedPress(scaled_mm(1.0, k), scaled_mm(-0.5, k), 2.5, size_mm=circle, shake_axis=axis,
                             shake_hz=hz) for hz in VIBRATE_HZ for axis in "xyz"]
    if experiment == "depths":
        presses = [PlannedPress(x, y, d, size_mm=circle) for x, y in depth_points(layout) for d in DEPTHS_MM
                   for _ in range(2)]
        return [presses[i] for i in rng.permutation(len(presses))]
    raise ValueError(f"unknown experiment {experiment!r} (known: {', '.join(EXPERIMENTS)})")
