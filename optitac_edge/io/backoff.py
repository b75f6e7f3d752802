"""Exponential backoff between attempts to reach a device that is not there (yet).

One helper for every place that retries: the service's camera reopen, the serial and CAN transports'
reconnect, the Zenoh publisher's session. Pure arithmetic, no clock: the caller waits the delay it gets
on its own clock (or stop event), so tests drive it without sleeping.
"""

from __future__ import annotations


class Backoff:
    """Delays ``first``, ``2 first``, ``4 first`` … capped at ``longest``, seconds; :meth:`reset` starts again.

    Parameters
    ----------
    first : float
        The first delay, s (> 0).
    longest : float
        The cap, s (at least ``first``: a smaller value is raised to it).

    Raises
    ------
    ValueError
        If ``first`` is not > 0.
    """

    def __init__(self, first: float, longest: float) -> None:
        if not first > 0:
            raise ValueError(f"the first backoff delay must be > 0 s, got {first!r}")
        self.first, self.longest = float(first), max(float(longest), float(first))
        self.delay = self.first

    def next(self) -> float:
        """The delay to wait now, s; the next one is twice as long (up to ``longest``)."""
        delay = self.delay
        self.delay = min(delay * 2.0, self.longest)
        return delay

    def reset(self) -> None:
        """After a success: the next delay is ``first`` again."""
        self.delay = self.first
