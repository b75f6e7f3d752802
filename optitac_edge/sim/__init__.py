"""The project's own camera-level simulator of an OptiTac sensor, with ground truth.

``optics``     :class:`CameraOptics`: camera geometry, lens, illumination, noise.
``skin``       :class:`Indenter`, :class:`SkinModel`, :func:`fiber_darkening`.
``render``     :class:`FrameRenderer`: per-fiber light -> uint8 frames, fast.
``sensor``     :class:`SimulatedSensor`: indenters -> frames, plus truth.
``scenarios``  :func:`write_scenario`: built-in recordings with ``truth.csv``.
``drift``      :class:`SessionDrift` (the "day" of a recording), :func:`sensor_variant`
               (other simulated sensors).
"""

from optitac_edge.sim.drift import NO_DRIFT, SessionDrift, sensor_variant, variant_optics, variant_sensor_seed
from optitac_edge.sim.optics import CameraOptics, Projection
from optitac_edge.sim.render import SENSOR_SEED, FrameRenderer, fiber_rest_peak
from optitac_edge.sim.scenarios import SCENARIOS, schedule, write_scenario
from optitac_edge.sim.sensor import SimulatedSensor
from optitac_edge.sim.skin import Indenter, SkinModel, fiber_darkening, signed_distance

__all__ = [
    "NO_DRIFT",
    "SCENARIOS",
    "SENSOR_SEED",
    "CameraOptics",
    "FrameRenderer",
    "Indenter",
    "Projection",
    "SessionDrift",
    "SimulatedSensor",
    "SkinModel",
    "fiber_darkening",
    "fiber_rest_peak",
    "schedule",
    "sensor_variant",
    "signed_distance",
    "variant_optics",
    "variant_sensor_seed",
    "write_scenario",
]
