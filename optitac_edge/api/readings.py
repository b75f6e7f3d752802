"""What a sensor reports: a frame's :class:`Reading` with its :class:`Contact` s, and the sensor's :class:`Status`.

Copies of the pipeline's values (they stay as they are). A value the sensor cannot know yet, or without its
calibration, is NaN in its field, so arrays of readings stay plain floats; each has a ``has_...`` property that
says whether it is known (``contact.has_depth`` rather than ``contact.depth_mm == contact.depth_mm``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from optitac_edge.core.contact import ContactEstimate
    from optitac_edge.core.frame_result import FrameResult


@dataclass(frozen=True, slots=True)
class Contact:
    """One contact of one frame (a copy: it stays as it is).

    Attributes
    ----------
    id : int
        1…255, the same from the contact's touch to its release.
    touch_frame : int
        The frame it touched in (``touch_frame == Reading.frame``: a new contact).
    x_mm, y_mm : float
        Centroid in the sensor frame, mm.
    major_mm, minor_mm, angle_deg : float
        FWHM widths along the principal axes, mm, and the major axis from +x, degrees (−90, 90].
    strength : float
        Darkening × area (the paper's m00).
    depth_mm, force_n : float
        Indentation depth (mm) and normal force (N); NaN without a depth / force calibration.
    shape : str
        The shape class (``""`` without a shape calibration).
    confidence : float
        The shape's posterior probability, 0…1 (NaN without a shape calibration).
    vx_mm_s, vy_mm_s : float
        Velocity, mm/s, from the last 5 centroids (NaN in the frame it touched in).
    sliding : bool
        It slides (gross motion above its own noise) rather than being held.
    slide_frame : int
        The frame its slide was found in; −1 while held.
    """

    id: int
    touch_frame: int
    x_mm: float
    y_mm: float
    major_mm: float
    minor_mm: float
    angle_deg: float
    strength: float
    depth_mm: float
    force_n: float
    shape: str
    confidence: float
    vx_mm_s: float
    vy_mm_s: float
    sliding: bool
    slide_frame: int

    @property
    def has_depth(self) -> bool:
        """The depth is known (a depth calibration); else ``depth_mm`` is NaN."""
        return not math.isnan(self.depth_mm)

    @property
    def has_force(self) -> bool:
        """The force is known (a depth calibration from a load cell's forces); else ``force_n`` is NaN."""
        return not math.isnan(self.force_n)

    @property
    def has_shape(self) -> bool:
        """The shape is known (a shape calibration); else ``shape`` is ``""`` and ``confidence`` NaN."""
        return bool(self.shape)

    @property
    def has_velocity(self) -> bool:
        """The velocity is known (not the frame it touched in); else ``vx_mm_s`` and ``vy_mm_s`` are NaN."""
        return not (math.isnan(self.vx_mm_s) or math.isnan(self.vy_mm_s))

    @classmethod
    def of(cls, c: ContactEstimate) -> Contact:
        """A copy of a pipeline's contact."""
        return cls(int(c.contact_id), int(c.touch_frame), float(c.x_mm), float(c.y_mm), float(c.major_mm),
                   float(c.minor_mm), float(c.angle_deg), float(c.strength), float(c.depth_mm), float(c.force_n),
                   c.shape or "", float(c.confidence), float(c.vx_mm_s), float(c.vy_mm_s), bool(c.sliding),
                   int(c.slide_frame))


@dataclass(frozen=True, slots=True)
class Reading:
    """What one camera frame gave one sensor (a copy).

    Attributes
    ----------
    sensor_id : int
    frame : int
        The sensor's frame counter, from 0.
    t_ns : int
        The frame's capture time, CLOCK_MONOTONIC ns (a recording's own times when replaying one).
    contacts : tuple of Contact
        Every contact, strongest first (0…4).
    released : tuple of int
        Ids of the contacts gone since the previous frame.
    vibration : float
        The fibers' energy above 20 Hz in units of their noise (about 1 at rest); NaN while it is learned.
    vibrating : bool
        The vibration is above its quiet level.
    baseline_ready : bool
        False during the first frames of a session (and after a tare), while the rest light is taken.
    saturated : bool
        Some fiber was at full scale.
    fibers : ndarray, shape (N,), float32, optional
        Each fiber's signal, layout order: its darkening from its rest light (a fraction of it with the default
        ``relative`` option, else gray levels; 0 for a dead fiber). Only from a sensor opened with ``arrays=True``
        (else None).
    surface : ndarray, shape (n, n), float32, optional
        The tactile surface: the pipeline's inverted surface in units of the level it is truncated at (its
        contact level, from the fibers' noise), 0 where below it. Only from a sensor opened with ``arrays=True``
        (else None).
    """

    sensor_id: int
    frame: int
    t_ns: int
    contacts: tuple[Contact, ...]
    released: tuple[int, ...]
    vibration: float
    vibrating: bool
    baseline_ready: bool
    saturated: bool
    fibers: np.ndarray | None = field(default=None, compare=False, repr=False)
    surface: np.ndarray | None = field(default=None, compare=False, repr=False)

    @property
    def has_vibration(self) -> bool:
        """The vibration is known (its quiet level is learned); else ``vibration`` is NaN."""
        return not math.isnan(self.vibration)

    @property
    def touching(self) -> bool:
        """Something touches the skin (at least one contact)."""
        return bool(self.contacts)

    @classmethod
    def of(cls, sensor_id: int, result: FrameResult, fibers: np.ndarray | None = None,
           surface: np.ndarray | None = None) -> Reading:
        """A copy of a pipeline's frame result (``fibers`` and ``surface``: arrays of its own, kept as given)."""
        return cls(sensor_id, int(result.frame), int(result.t_ns), tuple(Contact.of(c) for c in result.touching()),
                   tuple(cid for cid, _ in result.releases()), float(result.vibration), bool(result.vibrating),
                   bool(result.baseline_ready), bool(result.saturated), fibers, surface)


@dataclass(frozen=True, slots=True)
class Status:
    """How a sensor is doing.

    Attributes
    ----------
    sensor_id : int
    name : str
    frames : int
        Frames processed.
    contact_frames : int
        Frames with a contact.
    skipped : int
        Frames not processed: dark, saturated or not of the camera's shape (counted, never trusted).
    baseline_ready : bool
    calibration_id : str
        The bundle's id.
    compiled : bool
        The compiled kernel runs the frames (else the numpy pipeline).
    fps : float
        The camera's configured frame rate.
    dropped : int
        Frames the camera lost before they were read (a loop slower than the camera; gaps in its sequence).
    unread : int
        Readings made but never returned: replaced by a newer one before :meth:`Sensor.latest` was called, or
        read by :meth:`Sensor.tare` while it waited. ``frames == unread + readings returned``.
    """

    sensor_id: int
    name: str
    frames: int
    contact_frames: int
    skipped: int
    baseline_ready: bool
    calibration_id: str
    compiled: bool
    fps: float
    dropped: int = 0
    unread: int = 0
