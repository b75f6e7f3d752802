"""How far an experiment's presses go on an array (the rig's plans and the simulator's scenarios alike).

Sized for the paper's 217-fiber 1.5 mm array and following any other array's own radius, pitch and reach:
the ``unseen`` lines stay on the fibers, the ``depths`` rings reach as far out as presses go.
"""

from __future__ import annotations

import math

import numpy as np

from optitac_edge.core.layout import FiberLayout, scaled_mm

#: The ``depths`` experiment's presses reach as far out as the ``unseen`` ones (a circle of 5 paper-pitch mm
#: kept 0.5 inside the array: its centre this many pitches inside the rim).
DEPTH_REACH_PITCHES = 2.0
#: How far (pitches) a radial depth model is trusted beyond its outermost ring of presses: the paper's array's
#: ring half its radius out leaves exactly this much to its farthest press.
DEPTH_EXTRAPOLATION_PITCHES = 2.0


def depth_rings(layout: FiberLayout) -> list[float]:
    """The radii (mm) of the ``depths`` experiment's rings of 6 points around its centre press: half the
    radius out, as for the paper's array, and on a wider array also as far out as presses go
    (:data:`DEPTH_REACH_PITCHES` inside the rim), where half the radius would leave more than
    :data:`DEPTH_EXTRAPOLATION_PITCHES` to extrapolate (1027 fibers at 1.5 mm: 13.5 and 24 mm; the paper's
    217 and a 61-fiber 4 mm array: half the radius alone)."""
    half = 0.5 * layout.radius_mm
    far = layout.radius_mm - DEPTH_REACH_PITCHES * layout.pitch_mm
    return [half, far] if far - half > DEPTH_EXTRAPOLATION_PITCHES * layout.pitch_mm + 1e-9 else [half]


def depth_points(layout: FiberLayout) -> list[tuple[float, float]]:
    """Where the ``depths`` experiment presses, mm: the centre, then 6 points 60 degrees apart on each of
    :func:`depth_rings` (the bring-up's plan and the simulator's scenario both press here)."""
    return [(0.0, 0.0)] + [(ring * math.cos(math.radians(a)), ring * math.sin(math.radians(a)))
                           for ring in depth_rings(layout) for a in range(0, 360, 60)]


def axis_reach_mm(layout: FiberLayout, axis: int) -> float:
    """How far (mm) the array reaches from its centre along its x (``axis`` 0) or y (1) axis, either way: the
    farthest fiber within half a pitch of that axis (a hexagon of rows along x: its radius along x, the
    rows' reach, ``radius * sqrt(3) / 2``, along y)."""
    xy = layout.xy_mm
    near = np.abs(xy[:, 1 - axis]) < 0.5 * layout.pitch_mm
    return float(np.abs(xy[near, axis]).max(initial=0.0))


def unseen_line(layout: FiberLayout, axis: int, circle: float, step: float, k: float) -> np.ndarray:
    """The ``unseen`` presses' positions along the x (``axis`` 0) or y (1) axis: in ``step``s as far as the
    circle stays ``0.5`` (scaled) mm inside the array's radius, and its centre half a pitch inside the
    fibers' reach along that axis (:func:`axis_reach_mm`: a hexagon of rows along
    x reaches less far along y; on the paper's array, and on a 61-fiber 4 mm one, the radius decides)."""
    reach = min(layout.radius_mm - circle / 2 - scaled_mm(0.5, k),
                axis_reach_mm(layout, axis) - 0.5 * layout.pitch_mm)
    lim = math.floor(reach / step + 1e-9) * step
    return np.arange(-lim, lim + step / 2, step)
