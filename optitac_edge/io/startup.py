"""How long the service's start-up took, phase by phase, for the log (debug level).

Each :meth:`StartupTimes.mark` logs the time since the process started (the kernel's record of it,
``/proc/self/stat``, 10 ms ticks; elsewhere since this module was imported) and since the last mark:
``optitac-edge run -v`` shows where a slow start goes (imports, the board's config, the cameras and the
link opened, the bundles loaded, the pipelines and kernel plans built, the first frame processed).
"""

from __future__ import annotations

import logging
import os
import time

log = logging.getLogger("optitac_edge.startup")
_IMPORTED_S = time.monotonic()


def process_age_s() -> float:
    """Seconds since this process started (since this module's import where ``/proc`` cannot say)."""
    try:
        with open("/proc/self/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        started_s = int(fields[19]) / os.sysconf("SC_CLK_TCK")  # field 22 of the whole line: starttime
        return time.clock_gettime(time.CLOCK_BOOTTIME) - started_s
    except (OSError, ValueError, IndexError, AttributeError):
        return time.monotonic() - _IMPORTED_S


class StartupTimes:
    """The start-up's marks: each logged once, at debug level, with its time since the start and the last mark."""

    def __init__(self) -> None:
        self._last_s: float | None = None
        self.marks: list[tuple[str, float]] = []

    def mark(self, phase: str) -> None:
        """``phase`` has just ended."""
        age = process_age_s()
        since = age if self._last_s is None else age - self._last_s
        self._last_s = age
        self.marks.append((phase, age))
        log.debug("start-up: %s done %.0f ms after the process started (+%.0f ms)", phase, 1e3 * age, 1e3 * since)


#: The process's start-up (one per process: ``run`` and its session mark it).
STARTUP = StartupTimes()
