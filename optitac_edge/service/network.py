"""Contacts, status and the fiber signal on the robot's network, off the frame thread.

The frame loop calls :meth:`NetworkOutput.offer_frame` and
:meth:`NetworkOutput.offer_status`: each copies the frame's contacts into the
message objects (:class:`~optitac_edge.io.ros2.messages.ContactsSample`,
:class:`~optitac_edge.io.ros2.messages.StatusSample`) in a bounded queue and
returns (no encoding, no I/O, no lock held against the network). One
thread takes them out, encodes them as optitac_msgs (CDR) and hands them to a
:class:`~optitac_edge.io.publishers.Publisher`. A full queue drops its oldest
entry; the drops are counted per sensor (from gaps in each sensor's sequence)
and reported in every SensorStatus. A slow or absent subscriber costs the loop
nothing.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.frame_result import FrameResult
from optitac_edge.errors import PublishError
from optitac_edge.io.protocol.messages import TEMP_UNKNOWN, SensorState, StatusMessage
from optitac_edge.io.publishers.base import Publisher
from optitac_edge.io.ros2 import messages as msgs
from optitac_edge.io.ros2.rmw_zenoh import check_ros_name
from optitac_edge.io.threads import NamedThread

if TYPE_CHECKING:
    from typing_extensions import Self

log = logging.getLogger(__name__)

#: Entries the queue holds before it drops the oldest (about a second at 240 fps with 1 sensor).
DEFAULT_QUEUE = 256
#: How long closing waits for the queue to be sent (s); what is still queued then is dropped and counted.
CLOSE_WAIT_S = 5.0
#: Then how long it waits for the write under way (slow storage: an SD card's fsync) before leaving the
#: publisher open rather than closing it under the write (s).
WRITE_WAIT_S = 30.0

#: Points of a contact's outline on the image.
_OUTLINE_POINTS = 24


@dataclass(frozen=True)
class NetworkSensor:
    """A sensor as the network sees it.

    Attributes
    ----------
    sensor_id : int
    name : str
        The board config's name; its topics are ``<namespace>/optitac/<topic_name>/...``.
    x_mm, y_mm : ndarray, shape (N,)
        Fiber centres (the layout), for FiberSignal.
    dead : ndarray, shape (N,), bool
    calibration_id : str
    fiber_px : ndarray, shape (N, 2), optional
        Fiber centres (col, row) in the sensor's image (its region of the camera frame), for the overlay.
    region : tuple of int
        (x, y, width, height) of the sensor in the camera frame; () for the whole frame.
    image_rows : int
        The camera image's rows (a YUV420 frame holds more: its chroma planes).
    """

    sensor_id: int
    name: str
    x_mm: np.ndarray
    y_mm: np.ndarray
    dead: np.ndarray
    calibration_id: str = ""
    fiber_px: np.ndarray | None = None
    region: tuple[int, ...] = ()
    image_rows: int = 0

    def mm_to_px(self) -> np.ndarray:
        """The affine map (2, 3) from the sensor's surface (mm) to its image (px), fitted to the fibers."""
        assert self.fiber_px is not None
        mm = np.column_stack([self.x_mm, self.y_mm, np.ones_like(self.x_mm)]).astype(np.float64)
        live = ~self.dead
        coef, *_ = np.linalg.lstsq(mm[live], self.fiber_px[live], rcond=None)
        return np.asarray(coef.T)

    def crop(self, frame: np.ndarray) -> np.ndarray:
        """A copy of the sensor's image from a camera frame (the luma plane of a YUV420 frame)."""
        image = frame[:self.image_rows] if self.image_rows else frame
        if self.region:
            x, y, w, h = self.region
            image = image[y:y + h, x:x + w]
        return image.copy()

    @property
    def topic_name(self) -> str:
        """The sensor's name as a ROS 2 name token (``-`` and ``.`` become ``_``)."""
        return self.name.replace("-", "_").replace(".", "_")


def check_topic_names(sensors: Sequence[NetworkSensor]) -> None:
    """Every sensor's name makes a ROS 2 name token of its own.

    Raises
    ------
    PublishError
        Naming the sensor.
    """
    seen: dict[str, NetworkSensor] = {}
    for s in sensors:
        try:
            check_ros_name(s.topic_name, "its topic name")
        except ValueError as exc:
            raise PublishError(f"sensor {s.sensor_id} {s.name!r}: {exc}: rename the sensor to publish it") from None
        other = seen.setdefault(s.topic_name, s)
        if other is not s:
            raise PublishError(f"sensor {s.sensor_id} {s.name!r}: its topics would be sensor {other.sensor_id} "
                               f"{other.name!r}'s ({s.topic_name}): rename one of them")


def contact_values(c: ContactEstimate, frame: int) -> msgs.ContactValues:
    """A contact of ``frame`` as Contact.msg carries it."""
    return msgs.ContactValues(c.contact_id, c.touch_frame == frame, c.touch_frame, c.x_mm, c.y_mm, c.major_mm,
                              c.minor_mm, c.angle_deg, c.strength, c.depth_mm, c.force_n, c.shape or "",
                              c.confidence, c.vx_mm_s, c.vy_mm_s, c.sliding, c.slide_frame)


def contact_outline(mm_to_px: np.ndarray, contact: msgs.ContactValues) -> msgs.Outline:
    """A contact's ellipse (FWHM widths at its angle) in image pixels, labelled with its id and shape."""
    c = contact
    cid, x, y, major, minor, angle, shape = c.id, c.x_mm, c.y_mm, c.major_mm, c.minor_mm, c.angle_deg, c.shape
    t = np.linspace(0.0, 2 * np.pi, _OUTLINE_POINTS, endpoint=False)
    a = np.deg2rad(angle)
    ex, ey = major / 2 * np.cos(t), minor / 2 * np.sin(t)
    mm = np.column_stack([x + ex * np.cos(a) - ey * np.sin(a), y + ex * np.sin(a) + ey * np.cos(a),
                          np.ones_like(t)])
    px = mm @ mm_to_px.T
    cx, cy = mm_to_px @ np.array([x, y, 1.0])
    return msgs.Outline(px, f"{cid} {shape}".strip(), (float(cx), float(cy)))


def topic_of(namespace: str, sensor: NetworkSensor, what: str) -> str:
    """The fully qualified topic: ``<namespace>/optitac/<sensor>/<what>``."""
    return f"{namespace}/optitac/{sensor.topic_name}/{what}"


@dataclass(slots=True)
class _Picture:
    """The sensor's image, its surface and its contacts, for the picture topics (stamped with its entry's time)."""

    image: np.ndarray
    surface: np.ndarray | None
    contacts: list[msgs.ContactValues]


_Message = msgs.ContactsSample | msgs.StatusSample | msgs.SignalSample | _Picture


class _Queued(NamedTuple):
    """A message in the queue, with its sensor's slot, sequence number (gaps: drops) and time stamp."""

    slot: _Slot
    seq: int
    t_ns: int
    message: _Message


class _Slot:
    """One sensor's topics and counters (counters written by the publishing thread only)."""

    def __init__(self, sensor: NetworkSensor, handles: tuple[int, int, int | None], frame_id: str) -> None:
        self.sensor = sensor
        self.contacts_topic, self.status_topic, self.signal_topic = handles
        self.frame_id = frame_id
        self.offered = 0  # frame thread: entries offered
        self.taken = 0  # publishing thread: the last sequence taken
        self.published = 0
        self.dropped = 0
        self.previous_ids: set[int] = set()
        self.next_signal_ns = 0
        self.next_picture_ns = 0
        self.picture_topics: tuple[int, int, int] | None = None
        self.mm_to_px: np.ndarray | None = None


class NetworkOutput:
    """Publishes every sensor's contacts (every processed frame), status and signal from its own thread.

    Parameters
    ----------
    publisher : Publisher
        Opened by the caller; closed by :meth:`close`.
    sensors : sequence of NetworkSensor
    queue : int
        Entries held for the publishing thread before the oldest is dropped.
    signal_hz : float
        FiberSignal messages per second and sensor (0: none).
    picture_hz : float
        The sensor's camera image, its surface (both sensor_msgs/Image) and the fibers and contacts drawn
        over them (foxglove_msgs/ImageAnnotations) per second and sensor (0: none).
    """

    def __init__(self, publisher: Publisher, sensors: Sequence[NetworkSensor], queue: int = DEFAULT_QUEUE,
                 signal_hz: float = 0.0, picture_hz: float = 0.0) -> None:
        self.publisher = publisher
        ns = publisher.namespace
        self._slots: dict[int, _Slot] = {}
        check_topic_names(sensors)
        for s in sensors:
            handles = (publisher.advertise(topic_of(ns, s, "contacts"), msgs.CONTACTS),
                       publisher.advertise(topic_of(ns, s, "status"), msgs.STATUS),
                       publisher.advertise(topic_of(ns, s, "signal"), msgs.SIGNAL) if signal_hz > 0 else None)
            slot = self._slots[s.sensor_id] = _Slot(s, handles, f"optitac_{s.topic_name}")
            if picture_hz > 0:
                slot.picture_topics = (publisher.advertise(topic_of(ns, s, "image"), msgs.IMAGE),
                                       publisher.advertise(topic_of(ns, s, "surface"), msgs.IMAGE),
                                       publisher.advertise(topic_of(ns, s, "annotations"), msgs.ANNOTATIONS))
                slot.mm_to_px = s.mm_to_px() if s.fiber_px is not None else None
        self._signal_period_ns = int(1e9 / signal_hz) if signal_hz > 0 else 0
        self._picture_period_ns = int(1e9 / picture_hz) if picture_hz > 0 else 0
        self._queue: deque[_Queued] = deque(maxlen=queue)
        self._wake = threading.Event()
        self._stop = threading.Event()
        #: Closing gave up on the queue: the thread drops what is left (counted) and ends.
        self._abandon = threading.Event()
        self._left_open = False
        self.errors = 0
        self._thread = NamedThread(target=self._run, name="optitac-publish", daemon=True)
        self._thread.start()

    # -- the frame loop's side: copy and return ----------------------------------

    def offer_frame(self, sensor_id: int, result: FrameResult, degraded: bool, signal: np.ndarray | None = None,
                    frame: np.ndarray | None = None, surface: np.ndarray | None = None) -> None:
        """Every contact of a sensor's frame and its releases, and the signal and the picture (the camera
        ``frame``, the ``surface``) when due. Never blocks."""
        slot = self._slots[sensor_id]
        index, t_ns = result.frame, result.t_ns
        contacts = [contact_values(c, index) for c in result.touching()]
        released = sorted(cid for cid, _ in result.releases())
        sample = msgs.ContactsSample(sensor_id, index, t_ns, result.calibrated, result.saturated, degraded,
                                     contacts, released, result.vibration, result.vibrating)
        queue = self._queue
        slot.offered += 1
        queue.append(_Queued(slot, slot.offered, t_ns, sample))
        if self._signal_period_ns and signal is not None and t_ns >= slot.next_signal_ns:
            slot.next_signal_ns = t_ns + self._signal_period_ns
            slot.offered += 1
            s = slot.sensor
            queue.append(_Queued(slot, slot.offered, t_ns, msgs.SignalSample(sensor_id, index, s.x_mm, s.y_mm,
                                                                             signal.copy(), s.dead)))
        if self._picture_period_ns and frame is not None and t_ns >= slot.next_picture_ns:
            slot.next_picture_ns = t_ns + self._picture_period_ns
            slot.offered += 1
            picture = _Picture(slot.sensor.crop(frame), None if surface is None else surface.copy(), contacts)
            queue.append(_Queued(slot, slot.offered, t_ns, picture))
        self._wake.set()

    def offer_status(self, sensor_id: int, status: StatusMessage, state: SensorState, frames: int, contacts: int,
                     fps: float, protocol: int) -> None:
        """A sensor's STATUS (as the MCU gets it, with its flags) and its frame counts. Never blocks."""
        slot = self._slots[sensor_id]
        slot.offered += 1
        s, sensor = status, slot.sensor
        sample = msgs.StatusSample(
            sensor.sensor_id, sensor.name, sensor.calibration_id, fps, frames, contacts, s.frames_dropped,
            s.camera_errors, s.link_errors, 0, 0, math.nan if s.cpu_temp_c_x10 == TEMP_UNKNOWN
            else s.cpu_temp_c_x10 / 10, protocol, state.streaming, state.baseline_ready, state.degraded,
            state.camera_fault, state.light_change, state.calibration_unsaved)
        self._queue.append(_Queued(slot, slot.offered, s.t_us * 1000, sample))
        self._wake.set()

    # -- the publishing thread ----------------------------------------------------

    def _run(self) -> None:
        queue, wake = self._queue, self._wake
        while True:
            wake.wait(0.5)
            wake.clear()
            while queue:
                if self._abandon.is_set():
                    self._drop_queued()
                    return
                self._send(queue.popleft())
            if self._stop.is_set() and not queue:
                return

    def _drop_queued(self) -> None:
        """Closing gave up waiting: what is queued is dropped, each entry counted for its sensor."""
        while self._queue:
            slot, seq, _t, _message = self._queue.popleft()
            slot.dropped += seq - slot.taken
            slot.taken = seq

    def _send(self, item: _Queued) -> None:
        slot, seq, t_ns, message = item
        gap = seq - slot.taken - 1
        slot.dropped += gap
        slot.taken = seq
        wall = time.time_ns() - time.monotonic_ns()  # the frame clock (CLOCK_MONOTONIC) on the system clock
        try:
            if isinstance(message, msgs.ContactsSample):
                handle, payload = slot.contacts_topic, self._contacts_payload(slot, message, gap > 0, t_ns + wall)
            elif isinstance(message, _Picture):
                self._send_picture(slot, message, t_ns + wall)
                return
            elif isinstance(message, msgs.SignalSample):
                handle, payload = slot.signal_topic or 0, msgs.encode_signal(message, t_ns + wall, slot.frame_id)
            else:
                handle, payload = slot.status_topic, self._status_payload(slot, message, t_ns + wall)
            self.publisher.publish(handle, payload, time.time_ns())
            slot.published += 1
        except Exception as exc:  # noqa: BLE001 - the network never stops the service
            self.errors += 1
            if self.errors == 1:
                log.warning("publishing on %s failed: %s (counted; later failures at debug level)",
                            self.publisher.where, exc)
            else:
                log.debug("publishing failed: %s", exc)

    def _send_picture(self, slot: _Slot, picture: _Picture, stamp: int) -> None:
        """The sensor's image, its surface and the overlay, as three messages."""
        assert slot.picture_topics is not None
        image_topic, surface_topic, overlay_topic = slot.picture_topics
        now, s = time.time_ns(), slot.sensor
        self.publisher.publish(image_topic, msgs.encode_image(picture.image, stamp, slot.frame_id), now)
        slot.published += 1
        if picture.surface is not None:
            self.publisher.publish(surface_topic, msgs.encode_image(np.asarray(picture.surface, np.float32), stamp,
                                                                    slot.frame_id), now)
            slot.published += 1
        if s.fiber_px is not None and slot.mm_to_px is not None:
            outlines = [contact_outline(slot.mm_to_px, c) for c in picture.contacts]
            self.publisher.publish(overlay_topic, msgs.encode_annotations(stamp, s.fiber_px, s.dead, outlines), now)
            slot.published += 1

    def _contacts_payload(self, slot: _Slot, sample: msgs.ContactsSample, after_gap: bool, stamp: int) -> bytes:
        """The frame's contacts; after entries the queue dropped, the contacts of the last published frame
        that are gone are released too (their releases were in the dropped frames)."""
        ids = {c.id for c in sample.contacts}
        if after_gap and slot.previous_ids - ids:
            sample.released = sorted(set(sample.released) | (slot.previous_ids - ids))
        slot.previous_ids = ids
        return msgs.encode_contacts(sample, stamp, slot.frame_id)

    def _status_payload(self, slot: _Slot, sample: msgs.StatusSample, stamp: int) -> bytes:
        """The STATUS with the sensor's publishing counters as they are now."""
        sample.published, sample.publish_dropped = slot.published, slot.dropped
        return msgs.encode_status(sample, stamp, slot.frame_id)

    # -- counters and closing ------------------------------------------------------

    def counters(self, sensor_id: int) -> tuple[int, int]:
        """(messages published, entries dropped by the queue) of a sensor so far (a picture is up to three
        messages: image, surface, overlay)."""
        slot = self._slots[sensor_id]
        return slot.published, slot.dropped

    def close(self) -> None:
        """Send what is queued (for up to :data:`CLOSE_WAIT_S`; the rest dropped and counted), stop the thread,
        close the publisher once no write is under way (idempotent). A write that does not end within
        :data:`WRITE_WAIT_S` leaves the publisher open (its file stays as written, a ``.part``), never
        closed under it."""
        if not self._stop.is_set():
            self._stop.set()
            self._wake.set()
            self._thread.join(timeout=CLOSE_WAIT_S)
            if self._thread.is_alive():
                self._abandon.set()
                log.warning("publishing did not catch up within %g s of the stop: what is still queued is "
                            "dropped (counted)", CLOSE_WAIT_S)
                self._thread.join(timeout=WRITE_WAIT_S)
            if self._thread.is_alive():
                self._left_open = True
                log.warning("%s: a write did not end within %g s more; left open rather than closed under it",
                            self.publisher.where, WRITE_WAIT_S)
        if not self._left_open:
            self.publisher.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
