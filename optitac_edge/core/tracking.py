"""Stable contact ids and touch / release events from frame to frame.

Each frame's contacts are matched to the contacts of the previous frame:
the closest pair first (centroid distance), then the next closest among the
rest, as long as the distance is within the gate. A matched contact keeps
its id and the frame it touched in; an unmatched one is a new touch (a new
id); a contact of the previous frame left unmatched is released in this
frame. Ids are 1 … 255 (0: no contact), handed out in turn and never reused
while a contact holds one, so a receiver (the MCU) tells two contacts apart
and sees a press end and a new one start even at the same place.

At the camera's rate a contact moves a fraction of a millimetre per frame,
far less than the spacing of two contacts the segmentation keeps apart (a few
millimetres, see :mod:`~optitac_edge.core.segmentation`): the nearest match
within the gate is the same contact.

Plain Python on at most :data:`~optitac_edge.core.options.MAX_CONTACTS`
contacts; nothing is allocated per frame but a few floats.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from optitac_edge.core.contact import ContactEstimate

#: Largest contact id; ids run 1 … MAX_ID and wrap (0 means no contact).
MAX_ID = 255
#: The gate: the largest centroid step from one frame to the next that is the same contact, pitches of the
#: array (4 mm on the paper's 1.5 mm array).
GATE_PITCH = 4.0 / 1.5


class ContactTracker:
    """Gives the contacts of successive frames stable ids, touch frames and release events.

    Parameters
    ----------
    gate_mm : float
        Largest centroid distance between a contact and the previous frame's
        contact it continues, mm (> 0; the pipeline's: :data:`GATE_PITCH` pitches).
    max_contacts : int
        Most contacts per frame (the pipeline's ``max_contacts``).

    Attributes
    ----------
    released : list of (int, int)
        ``(contact id, touch frame)`` of the contacts released by the last
        :meth:`update` (valid ``[:n_released]``; reused).
    n_released : int
    """

    def __init__(self, gate_mm: float, max_contacts: int = 4) -> None:
        if not gate_mm > 0 or not math.isfinite(gate_mm):
            raise ValueError(f"tracking gate must be a finite distance > 0 mm, got {gate_mm!r}")
        self.gate_mm = float(gate_mm)
        self._gate2 = self.gate_mm * self.gate_mm
        self._max = int(max_contacts)
        # the previous frame's contacts: (x, y, id, touch frame)
        self._prev: list[tuple[float, float, int, int]] = []
        self._next_id = 1
        self.released: list[tuple[int, int]] = [(0, -1)] * self._max
        self.n_released = 0

    def reset(self) -> None:
        """Forget every contact (a tare): the next frame's contacts are new touches; nothing is released."""
        self._prev.clear()
        self.n_released = 0

    def _new_id(self, taken: set[int]) -> int:
        cid = self._next_id
        while cid in taken:  # at most max_contacts ids are taken
            cid = cid % MAX_ID + 1
        self._next_id = cid % MAX_ID + 1
        return cid

    def update(self, contacts: Sequence[ContactEstimate], n: int, frame: int, separate: bool = False) -> None:
        """Match the first ``n`` of ``contacts`` (one frame's) to the previous frame's, in place.

        Sets ``contact_id`` and ``touch_frame`` of each (``touch_frame == frame``:
        it touched in this frame) and fills :attr:`released` with the previous
        frame's contacts that are gone. ``separate``: the frame follows a gap (a snapshot): every previous
        contact is released and every contact is a new touch.
        """
        prev = self._prev
        n_prev = len(prev)
        match = [-1] * n  # index into prev, per contact
        if n and n_prev and not separate:
            pairs = []
            for i in range(n):
                c = contacts[i]
                x, y = c.x_mm, c.y_mm
                for j in range(n_prev):
                    px, py = prev[j][0], prev[j][1]
                    d2 = (x - px) * (x - px) + (y - py) * (y - py)
                    if d2 <= self._gate2:  # NaN never is
                        pairs.append((d2, i, j))
            pairs.sort()
            used = [False] * n_prev
            for _d2, i, j in pairs:
                if match[i] < 0 and not used[j]:
                    match[i], used[j] = j, True
        kept = {prev[j][2] for j in match if j >= 0}
        r = 0
        for j in range(n_prev):
            if prev[j][2] not in kept:
                self.released[r] = (prev[j][2], prev[j][3])
                r += 1
        self.n_released = r
        taken = {p[2] for p in prev}  # a released id is not handed out again in the same frame
        current = []
        for i in range(n):
            c = contacts[i]
            j = match[i]
            if j >= 0:
                c.contact_id, c.touch_frame = prev[j][2], prev[j][3]
            else:
                c.contact_id, c.touch_frame = self._new_id(taken), frame
                taken.add(c.contact_id)
            current.append((c.x_mm, c.y_mm, c.contact_id, c.touch_frame))
        self._prev = current
