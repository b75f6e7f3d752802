"""Simulated sensors of other arrays than the paper's: what scales with the pitch.

The simulator's skin and camera are sized for the paper's 217-fiber array at
1.5 mm (:data:`~optitac_edge.core.layout.PAPER_PITCH_MM`). A layout of another
pitch (a 61-fiber array at 4 mm, say) is the same skin at another scale: every
lateral length of the skin (the spread of its deflection, the clamp's margin
and width, an edge indenter's bar, the deflection grid, the tilt's spread) and
the fiber end faces grow with the pitch; depths stay in mm (the indenter goes
as deep into any skin). At the paper's pitch nothing changes.
"""

from __future__ import annotations

from dataclasses import replace

from optitac_edge.core.layout import FiberLayout, pitch_scale
from optitac_edge.sim.optics import CameraOptics
from optitac_edge.sim.skin import SkinModel

#: The skin's lateral lengths, mm (scaled with the pitch).
LATERAL_SKIN_FIELDS = ("spread_mm", "spread_per_depth", "clamp_margin_mm", "rim_width_mm", "edge_length_mm",
                       "grid_step_mm", "tilt_spread_mm")


def skin_for(layout: FiberLayout, skin: SkinModel) -> SkinModel:
    """``skin`` (sized for the paper's array) for ``layout``: its lateral lengths times the pitch scale."""
    k = pitch_scale(layout)
    return skin if k == 1.0 else replace(skin, **{f: getattr(skin, f) * k for f in LATERAL_SKIN_FIELDS})


def optics_for(layout: FiberLayout, optics: CameraOptics) -> CameraOptics:
    """``optics`` for ``layout``: the fiber end faces times the pitch scale."""
    k = pitch_scale(layout)
    return optics if k == 1.0 else replace(optics, fiber_diameter_mm=optics.fiber_diameter_mm * k)
