"""Indentation rigs behind one interface (:class:`~optitac_edge.io.rigs.base.Rig`), chosen by URL."""

from optitac_edge.io.rigs.base import Rig, RigLimits, RigStatus

__all__ = ["Rig", "RigLimits", "RigStatus"]
