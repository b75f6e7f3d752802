"""What the MCU has been told: the touches and releases of each frame sent in protocol v2.

The pipeline's tracker gives every contact a stable id and releases it in the
frame it is gone (:class:`~optitac_edge.core.frame_result.FrameResult`); the link
may send only every n-th frame (STREAM's rate divider) or none for a while
(streaming off). So the events on the wire are relative to the frames the MCU
received: a contact is a TOUCH in the first sent frame that holds it, and the
tracker's RELEASE of a contact the MCU was told of goes out with the next sent
frame. No contact is released without having been announced, and none is lost
between sent frames. Pure logic, no I/O.
"""

from __future__ import annotations

from optitac_edge.core.frame_result import FrameResult


class ContactAnnouncer:
    """The ids the receiver holds as touching, their touch frames, and their releases not yet sent."""

    def __init__(self) -> None:
        self._told: dict[int, int] = {}  # contact id -> touch frame, in the order they were last sent
        self._gone: set[tuple[int, int]] = set()  # told contacts the tracker released since the last send
        #: Contacts of the last :meth:`announce` that are new to the receiver, by index.
        self.touched: list[bool] = []

    def reset(self) -> None:
        """The receiver knows nothing (a new protocol session): every contact is a touch again."""
        self._told.clear()
        self._gone.clear()

    def observe(self, result: FrameResult) -> None:
        """Every processed frame, sent or not: note the tracker's releases of contacts the receiver holds."""
        told = self._told
        for k in range(result.n_released):
            cid, touch = result.released[k]
            if told.get(cid) == touch:
                self._gone.add((cid, touch))

    def announce(self, result: FrameResult) -> list[tuple[int, int]]:
        """A frame is sent: the releases ``(contact id, touch frame)`` to send with it (oldest told first).

        Sets :attr:`touched` for the frame's contacts and remembers them as told.
        Call after :meth:`observe` of the same frame.
        """
        gone = self._gone
        released = [(cid, touch) for cid, touch in self._told.items() if (cid, touch) in gone] if gone else []
        gone.clear()
        contacts, n = result.contacts, result.n_contacts
        told = self._told
        self.touched = [told.get(contacts[i].contact_id) != contacts[i].touch_frame for i in range(n)]
        self._told = {contacts[i].contact_id: contacts[i].touch_frame for i in range(n)}
        return released
