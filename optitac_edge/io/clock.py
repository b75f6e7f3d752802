"""The clock the service and the simulated devices run on: the system's, or a virtual one.

Everything that reads the time or waits takes a :class:`Clock` (default
:data:`SYSTEM_CLOCK`, CLOCK_MONOTONIC). A :class:`VirtualClock` moves only
when someone sleeps or waits on it, so a loop driven by it (the service with
the simulated camera, the soak run, the tests) gives the same counts for the
same seed on any machine, as fast as the machine can compute.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol


class Clock(Protocol):
    """Monotonic time and waiting on it."""

    def monotonic_ns(self) -> int:
        """Now, ns (CLOCK_MONOTONIC for the system clock)."""

    def sleep(self, seconds: float) -> None:
        """Wait ``seconds`` (nothing for ``seconds <= 0``)."""

    def wait(self, event: threading.Event, seconds: float) -> bool:
        """Wait until ``event`` is set or ``seconds`` passed; whether it is set."""


class SystemClock:
    """The machine's CLOCK_MONOTONIC."""

    def monotonic_ns(self) -> int:
        return time.monotonic_ns()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)

    def wait(self, event: threading.Event, seconds: float) -> bool:
        return event.wait(max(seconds, 0.0))


#: The clock of everything that runs for real.
SYSTEM_CLOCK = SystemClock()


class VirtualClock:
    """A clock that advances only when it is slept or waited on (or :meth:`advance`\\ d).

    Waiting on an event returns at once when the event is set; otherwise the
    time jumps by the timeout. Meant for one thread driving the time (the
    frame loop); other threads may read it.

    Parameters
    ----------
    start_ns : int
        The time it starts at, ns.
    """

    def __init__(self, start_ns: int = 0) -> None:
        self._now = int(start_ns)
        self._lock = threading.Lock()

    def monotonic_ns(self) -> int:
        return self._now

    def advance(self, seconds: float) -> None:
        """Move the time forward by ``seconds`` (>= 0)."""
        if seconds < 0:
            raise ValueError(f"a clock cannot go back ({seconds} s)")
        with self._lock:
            self._now += round(seconds * 1e9)

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.advance(seconds)

    def wait(self, event: threading.Event, seconds: float) -> bool:
        if event.is_set():
            return True
        self.sleep(seconds)
        return event.is_set()
