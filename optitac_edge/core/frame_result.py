"""What one frame gave: its contacts, their touches and releases, and the frame's flags.

:meth:`Pipeline.process <optitac_edge.core.pipeline.Pipeline.process>` fills one
:class:`FrameResult` in place every frame and returns it; everything
downstream (the messages to the MCU, the network, the contacts CSV, the live
view) reads the frame from it, so a contact has one shape on its way out
(:class:`~optitac_edge.core.contact.ContactEstimate`) and its releases are
computed once (by :class:`~optitac_edge.core.tracking.ContactTracker`).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

from optitac_edge.core.contact import ContactEstimate


@dataclass(slots=True, eq=False)
class FrameResult:
    """One frame's result, reused (updated in place) by its pipeline every frame.

    Attributes
    ----------
    primary : ContactEstimate
        The frame's estimate: its strongest contact, or, without contact, the
        strength and area below the contact level. The same object as ``contacts[0]``.
    frame : int
        The frame's index among those its pipeline processed, from 0.
    t_ns : int
        The frame's timestamp, ns (given with the frame).
    baseline_ready : bool
        False while the first ``baseline_frames`` frames are averaged into the
        baseline (then there is no contact and the primary estimate is NaN/0).
    contacts : list of ContactEstimate
        Every contact of the frame, strongest first; valid ``[:n_contacts]``.
        Each has its stable ``contact_id`` and ``touch_frame`` (``touch_frame ==
        frame``: it touched in this frame).
    n_contacts : int
        0 without contact.
    released : list of (int, int)
        ``(contact id, touch frame)`` of the previous frame's contacts that are
        gone in this one; valid ``[:n_released]``.
    n_released : int
    light_changed : bool
        The frame's light changed common-mode (an LED dimming or brightening, not a contact).
    baseline_raised : bool
        The frame raised the baseline of fibers brighter than it (it had been taken over a press).
    raised_fibers : int
        How many fibers the last raise moved.
    saturated : bool
        Some live fiber centre of the frame is at full scale (the frame check's flag, carried).
    calibrated : bool
        The centroid and width calibrations were applied to the contacts.
    vibration : float
        The fibers' signal energy above the vibration cut-off, in units of its level at rest
        (:class:`~optitac_edge.core.vibration.VibrationMeter`); NaN until the rest level is learned.
    vibrating : bool
        The vibration is above its quiet level (the meter's hysteresis).
    vibration_began : bool
        ``vibrating`` turned on in this frame (the event).
    """

    contacts: list[ContactEstimate]
    released: list[tuple[int, int]]
    primary: ContactEstimate = field(init=False)
    frame: int = -1
    t_ns: int = 0
    baseline_ready: bool = False
    n_contacts: int = 0
    n_released: int = 0
    light_changed: bool = False
    baseline_raised: bool = False
    raised_fibers: int = 0
    saturated: bool = False
    calibrated: bool = False
    vibration: float = math.nan
    vibrating: bool = False
    vibration_began: bool = False

    def __post_init__(self) -> None:
        self.primary = self.contacts[0]

    def touching(self) -> Iterator[ContactEstimate]:
        """The frame's contacts, strongest first."""
        contacts = self.contacts
        for k in range(self.n_contacts):
            yield contacts[k]

    def releases(self) -> list[tuple[int, int]]:
        """``(contact id, touch frame)`` of the contacts this frame released (a new list)."""
        return self.released[:self.n_released]
