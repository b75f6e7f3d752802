"""Deliberately different simulated physics: the skins a real OptiTac may turn out to be.

Our simulator is one guess at how a skin darkens its fibers. A calibration
that only works on that guess is not yet one that works on a real skin, so
every model is calibrated and evaluated, with the same code and no setting of
its own, on each of these physics (``optitac-edge sim --physics NAME``,
``sim://?physics=NAME``, ``tools/accuracy_table.py``). They bracket what a
real skin may do; docs/simulator.md describes each.

=============  ==========================================================================
``default``    the simulator's own guess: a mildly saturating response, flat punch,
               the clamped rim over 6 mm
``linear``     the darkening grows in proportion to the deflection (half the gains),
               clipped where a fiber is fully dark
``saturating`` a response that saturates inside the indenter (2.7x the compression
               gain): the darkening's top flattens early, the width grows little
``threshold``  pins that stick: nothing turns until ``s`` exceeds 0.15
``sphere``     every indenter a dome (a 5 mm circle is a 5 mm ball): the footprint
               grows with depth
``soft-rim``   a skin clamped loosely (rim over 2.5 mm, 0.3x rim stiffening)
``stiff-rim``  a skin clamped hard (rim over 12 mm, 3x stiffer at the rim)
``wide-tilt``  pins that tilt 2 mm further out than the skin deflects, twice as much
``drifty``     the default skin with 3x the LED and pin drift between days
               (±6-15 % instead of ±2-5 %)
``real``       the statistics a real fiber sensor showed (:mod:`optitac_edge.sim.real`): 61
               colour-coded fibers at 4 mm under the default skin scaled to them, each
               fiber's light wandering by a few percent over minutes (the outer ring
               most, one fiber brightening 39 % in half an hour), up to 30 % between
               days, stray light in the image corners, a webcam's RGB frames
=============  ==========================================================================
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

from optitac_edge.sim.real import REAL_OPTICS, REAL_PITCH_MM, REAL_RINGS, FiberWander
from optitac_edge.sim.skin import SkinModel

_BASE = SkinModel()


@dataclass(frozen=True)
class Physics:
    """One simulated physics: a skin, and how much it drifts between days.

    Attributes
    ----------
    name : str
    summary : str
        One line for a person.
    skin : SkinModel
        The default sensor's skin under this physics (a sensor variant scales its fields).
    day_drift : float
        Scale of the LED and pin gain changes between days (``SessionDrift.for_day``'s ``scale``).
    array : (int, float) or None
        The hexagonal array (rings, pitch mm) a recording of this physics has unless a layout is given
        (None: the paper's 217 fibers at 1.5 mm).
    optics : mapping
        The camera's fields this physics sets (:class:`~optitac_edge.sim.optics.CameraOptics`).
    wander : FiberWander or None
        Each fiber's light wandering over time and between days.
    colour_coded : bool
        Colour-coded fibers under a coloured skin (RGB frames).
    """

    name: str
    summary: str
    skin: SkinModel
    day_drift: float = 1.0
    array: tuple[int, float] | None = None
    optics: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    wander: FiberWander | None = None
    colour_coded: bool = False


PHYSICS: dict[str, Physics] = {p.name: p for p in (
    Physics("default", "the simulator's own guess", _BASE),
    Physics("linear", "darkening in proportion to the deflection",
            replace(_BASE, response="linear", compression_gain=0.22, tilt_gain=0.2)),
    Physics("saturating", "a response that saturates inside the indenter",
            replace(_BASE, compression_gain=1.2, tilt_gain=0.6, spread_per_depth=0.02)),
    Physics("threshold", "pins that stick until pushed far enough", replace(_BASE, response="threshold")),
    Physics("sphere", "domed indenters: the footprint grows with depth", replace(_BASE, dome=1.0)),
    Physics("soft-rim", "a skin clamped loosely at its rim",
            replace(_BASE, rim_width_mm=2.5, rim_stiffening=0.3)),
    Physics("stiff-rim", "a skin clamped hard at its rim",
            replace(_BASE, rim_width_mm=12.0, rim_stiffening=3.0)),
    Physics("wide-tilt", "pins that tilt beyond the indenter", replace(_BASE, tilt_spread_mm=2.0, tilt_gain=0.8)),
    Physics("drifty", "3x the LED and pin drift between days", _BASE, day_drift=3.0),
    Physics("real", "a real 61-fiber sensor's statistics: fibers that wander, days apart, colour, stray light",
            _BASE, array=(REAL_RINGS, REAL_PITCH_MM), optics=MappingProxyType({**REAL_OPTICS, "rgb": True}),
            wander=FiberWander(), colour_coded=True),
)}

#: The names of :data:`PHYSICS`, in order.
PHYSICS_NAMES = tuple(PHYSICS)


def physics(name: str) -> Physics:
    """The physics called ``name``.

    Raises
    ------
    ValueError
        One line naming the unknown physics and the known ones.
    """
    try:
        return PHYSICS[name]
    except KeyError:
        raise ValueError(f"unknown simulated physics {name!r} (known: {', '.join(PHYSICS_NAMES)})") from None
