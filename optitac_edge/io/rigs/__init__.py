"""Indentation rigs behind one interface (:class:`~optitac_edge.io.rigs.base.Rig`), chosen by URL scheme.

``gcode://PORT``  a GRBL machine on a serial port or pyserial URL (:mod:`optitac_edge.io.rigs.gcode`).
``ur://HOST``     a Universal Robots arm through ``ur_rtde`` (extra ``[ur]``, :mod:`optitac_edge.io.rigs.ur`).
``sim://?...``    the simulator's virtual rig and its camera on a virtual clock (:mod:`optitac_edge.sim.rig`,
                  added from the layer above through the ``optitac_edge.rigs`` entry point group).

Adding one is a module with its :class:`Rig` subclass (``from_url``) and a line in :data:`RIGS`.
"""

from optitac_edge.errors import RigError
from optitac_edge.io.registry import Backend, Registry
from optitac_edge.io.rigs.base import Rig, RigConfig, RigLimits, RigStatus

#: URL scheme -> the rig's class, imported on first use.
RIGS: Registry[Rig] = Registry("rig", RigError, {
    "gcode": "optitac_edge.io.rigs.gcode:GcodeRig",
    "ur": Backend("optitac_edge.io.rigs.ur:UrRig", extra="ur"),
}, group="optitac_edge.rigs")

__all__ = ["RIGS", "Rig", "RigConfig", "RigLimits", "RigStatus"]
