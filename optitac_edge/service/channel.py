"""One sensor of a camera's frames: its pipeline, frame check, messages to the MCU and STATUS flags.

A camera may read several sensors (fiber patches in their own regions of the
frame); the frame loop (:mod:`optitac_edge.service.loop`) runs one
:class:`SensorChannel` per sensor on every frame. Everything here is filled in
place: no allocation per frame beyond what the pipeline does.
"""

from __future__ import annotations

import logging

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.fingerprint import SensorMismatchError
from optitac_edge.core.frame_engine import Skip
from optitac_edge.core.frame_result import FrameResult
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.io.cameras.base import CapturedFrame
from optitac_edge.io.protocol.messages import StatusMessage
from optitac_edge.io.protocol.outbox import SensorOutbox
from optitac_edge.io.protocol.packet import Packer

log = logging.getLogger(__name__)


class SensorChannel:
    """One sensor read from a camera: everything the loop keeps per sensor.

    Parameters
    ----------
    sensor_id : int
        0..255, what the MCU hears in every message.
    name : str
        For logs.
    bundle : CalibrationBundle
        Its calibration, placed in the camera's whole frame.
    fps : float, optional
        The camera's nominal frame rate (the pipeline's motion and vibration period).
    packer : Packer, optional
        The link's packer of this sensor's messages (``transport.packer(sensor_id)``; default serial).
    """

    def __init__(self, sensor_id: int, name: str, bundle: CalibrationBundle, fps: float | None = None,
                 packer: Packer | None = None) -> None:
        self.sensor_id = sensor_id
        self.name = name
        self.bundle = bundle
        self.pipeline = Pipeline(bundle, fps=fps, source=f"{name}'s camera frames")
        #: Some fiber of the bundle is dead (every message's DEGRADED flag).
        self.degraded = bool(bundle.fibers.dead.any())
        #: The messages of each frame to the MCU.
        self.outbox = SensorOutbox(sensor_id, self.degraded, packer)
        self.status = StatusMessage(sensor_id=sensor_id, calibration_id=int(bundle.calibration_id[:8] or "0", 16))
        #: Frames this sensor processed, and those with a contact.
        self.frames = 0
        self.contacts = 0
        #: A frame of this sensor was skipped, or failed, since the last STATUS.
        self.fault_since_status = False
        #: A common-mode change of the light since the last STATUS.
        self.light_since_status = False
        self._captured: CapturedFrame | None = None

    @property
    def mismatch(self) -> str | None:
        """Why the camera's frames are not of this sensor's bundle (then no frame is processed), or None."""
        refused = self.pipeline.mismatch
        return None if refused is None else str(refused)

    def take(self, captured: CapturedFrame) -> None:
        """The checked frame :meth:`run_pipeline` processes next."""
        self._captured = captured

    def run_pipeline(self) -> FrameResult | Skip:
        """The pipeline on the frame :meth:`take` gave (on a worker thread of the loop's pool, or the loop's):
        its result, or why the frame was skipped (:meth:`Pipeline.process
        <optitac_edge.core.pipeline.Pipeline.process>`)."""
        c = self._captured
        assert c is not None, "take() a frame first"
        if self.pipeline.mismatch is not None:
            return Skip.MISMATCH
        try:
            return self.pipeline.process(c.frame, c.t_ns)
        except SensorMismatchError as exc:
            log.error("sensor %d: %s; no contacts are sent (STATUS: baseline not ready, camera fault)",
                      self.sensor_id, exc)
            return Skip.MISMATCH

    def replace_pipeline(self, pipeline: Pipeline) -> None:
        """Use ``pipeline`` from the next frame (a re-oriented bundle, built off the frame thread); it goes on
        with this one's contact ids, so the contacts of the old one are released."""
        pipeline.adopt_tracking(self.pipeline)
        self.pipeline = pipeline
