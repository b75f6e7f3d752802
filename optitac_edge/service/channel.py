"""One sensor of a camera's frames: its pipeline, frame check, messages to the MCU and STATUS flags.

A camera may read several sensors (fiber patches in their own regions of the
frame); the frame loop (:mod:`optitac_edge.service.loop`) runs one
:class:`SensorChannel` per sensor on every frame. Everything here is filled in
place: no allocation per frame beyond what the pipeline does.
"""

from __future__ import annotations

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.frame_check import FrameCheck
from optitac_edge.core.options import MAX_CONTACTS
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.io.protocol.announce import ContactAnnouncer
from optitac_edge.io.protocol.messages import ContactMessage, ContactV2Message, ReleaseMessage, StatusMessage


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
    frame_shape : tuple of int
        The camera's frame shape (the frame check's expectation).
    """

    def __init__(self, sensor_id: int, name: str, bundle: CalibrationBundle, frame_shape: tuple[int, ...]) -> None:
        self.sensor_id = sensor_id
        self.name = name
        self.bundle = bundle
        self.pipeline = Pipeline(bundle)
        self.frame_check = FrameCheck(bundle.fibers, frame_shape)
        self.message = ContactMessage(sensor_id=sensor_id)
        self.messages_v2 = [ContactV2Message(sensor_id=sensor_id) for _ in range(MAX_CONTACTS)]
        self.release = ReleaseMessage(sensor_id=sensor_id)
        self.announcer = ContactAnnouncer()
        self.status = StatusMessage(sensor_id=sensor_id, calibration_id=int(bundle.calibration_id[:8] or "0", 16))
        #: Some fiber of the bundle is dead (every message's DEGRADED flag).
        self.degraded = bool(bundle.fibers.dead.any())
        #: Frames this sensor processed, and those with a contact.
        self.frames = 0
        self.contacts = 0
        #: A frame of this sensor was skipped, or failed, since the last STATUS.
        self.fault_since_status = False
        #: A common-mode change of the light since the last STATUS.
        self.light_since_status = False

    def replace_pipeline(self, pipeline: Pipeline) -> None:
        """Use ``pipeline`` from the next frame (a re-oriented bundle, built off the frame thread)."""
        self.pipeline = pipeline

    def fill_v1(self, est: ContactEstimate, t_ns: int, now_ns: int, saturated: bool) -> ContactMessage:
        """The frame's CONTACT (protocol v1: its primary contact)."""
        return self.message.fill(est, t_ns, now_ns, self.pipeline.calibrated, saturated=saturated,
                                 degraded=self.degraded)

    def releases(self, est: ContactEstimate) -> list[tuple[int, int]]:
        """Protocol v2: (id, touch frame) of every contact the MCU was told of that is gone this frame."""
        return self.announcer.update(self.pipeline.contacts, est.n_contacts if est.contact else 0)

    def fill_v2(self, est: ContactEstimate, k: int, t_ns: int, now_ns: int, saturated: bool) -> ContactV2Message:
        """Protocol v2: the CONTACT2 of contact ``k`` (after :meth:`releases`); with no contact, one saying so."""
        n = est.n_contacts if est.contact else 0
        return self.messages_v2[k].fill(self.pipeline.contacts[k] if n else est, k, t_ns, now_ns,
                                        self.pipeline.calibrated, saturated, self.degraded,
                                        touch=self.announcer.touched[k] if n else None)
