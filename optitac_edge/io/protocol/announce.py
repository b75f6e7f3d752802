"""What the MCU has been told: the touches and releases of each frame sent in protocol v2.

The pipeline's tracker gives every contact a stable id; the link may send only
every n-th frame (STREAM's rate divider) or none for a while (streaming off).
So the events on the wire are relative to the frames the MCU received: a
contact is a TOUCH in the first sent frame that holds it, and a RELEASE goes
out in the first sent frame that no longer holds it. No contact is released
without having been announced, and none is lost between sent frames. Pure
logic, no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any


class ContactAnnouncer:
    """The ids the receiver holds as touching, and their touch frames."""

    def __init__(self) -> None:
        self._told: dict[int, int] = {}  # contact id -> touch frame
        #: Contacts of the last :meth:`update` that are new to the receiver, by index.
        self.touched: list[bool] = []

    def reset(self) -> None:
        """The receiver knows nothing (a new protocol session): every contact is a touch again."""
        self._told.clear()

    def update(self, contacts: Sequence[Any], n: int) -> list[tuple[int, int]]:
        """The releases ``(contact id, touch frame)`` to send with a frame holding ``contacts[:n]``.

        Sets :attr:`touched` for those contacts and remembers them as told.
        """
        current = {int(contacts[i].contact_id): int(contacts[i].touch_frame) for i in range(n)}
        released = [(cid, touch) for cid, touch in self._told.items()
                    if cid not in current or current[cid] != touch]  # an id handed out again is a new contact
        self.touched = [self._told.get(int(contacts[i].contact_id)) != int(contacts[i].touch_frame)
                        for i in range(n)]
        self._told = current
        return released
