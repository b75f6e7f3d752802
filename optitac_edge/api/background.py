"""A sensor read in a thread of its own, so that a control loop slower than the camera takes the newest reading
without waiting for a frame (:meth:`optitac_edge.api.Sensor.start`)."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from optitac_edge.api.readings import Reading
from optitac_edge.errors import OptiTacError
from optitac_edge.io.threads import NamedThread

log = logging.getLogger(__name__)

#: ``step(timeout_s)`` reads and processes one frame: (its reading, or None when the check refused the frame;
#: True once the source has ended).
Step = Callable[[float], tuple[Reading | None, bool]]


class BackgroundReader:
    """Runs ``step`` in a thread until :meth:`stop`; keeps the newest reading for :meth:`take`.

    Every reading the thread makes is either returned by :meth:`take` or counted in :attr:`unread` (a newer
    one replaced it first): ``made == returned + unread`` at all times. A failure of ``step`` (the camera) ends
    the thread; the next :meth:`take` raises it.

    Parameters
    ----------
    step : callable
        ``step(timeout_s)``, see :data:`Step`. Called from the thread only.
    tare : callable
        Takes the rest light again; called from the thread only, between two frames.
    timeout_s : float
        The longest wait for one frame (the camera's ``timeout_s``).
    name : str
        The thread's name.
    """

    def __init__(self, step: Step, tare: Callable[[], None], timeout_s: float, name: str) -> None:
        self._step, self._tare, self._timeout_s = step, tare, timeout_s
        self._cond = threading.Condition()
        self._latest: Reading | None = None
        self._taken = True  # the newest reading was returned (or there is none)
        #: Readings made, returned by :meth:`take`, and replaced before one returned them.
        self.made = self.returned = self.unread = 0
        self._error: Exception | None = None
        self._ended = False
        self._tares_asked = self._tares_done = 0
        self._tare_ready = False  # a reading after the last tare done had its baseline ready
        self._stopping = threading.Event()
        self._thread = NamedThread(target=self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def running(self) -> bool:
        """The thread reads frames (not stopped, not ended, not failed)."""
        return self._thread.is_alive()

    def _run(self) -> None:
        try:
            while not self._stopping.is_set():
                asked = self._tares_asked  # an int read once a frame: no lock taken for it (one fewer a frame)
                if asked != self._tares_done:
                    self._tare()
                    with self._cond:
                        self._tares_done, self._tare_ready = asked, False
                reading, ended = self._step(self._timeout_s)
                with self._cond:
                    if ended:
                        self._ended = True
                        self._cond.notify_all()
                        return
                    if reading is None:
                        continue
                    if not self._taken:
                        self.unread += 1
                    self._latest, self._taken = reading, False
                    self.made += 1
                    self._tare_ready = self._tare_ready or (reading.baseline_ready
                                                            and self._tares_done == self._tares_asked)
                    self._cond.notify_all()
        except Exception as exc:  # noqa: BLE001  (handed to the caller: its next take() raises it)
            with self._cond:
                self._error = exc
                self._cond.notify_all()

    def take(self, timeout_s: float) -> Reading | None:
        """The newest reading not yet returned, waiting up to ``timeout_s`` for one; None if none came (or
        the source ended).

        Raises
        ------
        Exception
            What ended the thread (a camera's failure: an OptiTacError), once.
        """
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._taken and self._error is None and not self._ended:
                left = deadline - time.monotonic()
                if left <= 0 or not self._thread.is_alive():
                    return None
                self._cond.wait(left)
            if self._error is not None and self._taken:
                error, self._error = self._error, None
                raise error
            if self._taken:  # ended, nothing new
                return None
            self._taken = True
            self.returned += 1
            return self._latest

    def tare(self, wait_s: float | None) -> bool:
        """Take the rest light again before the next frame; with ``wait_s``, wait up to that long for a reading
        whose baseline is ready. Returns whether one was (False at once without ``wait_s``)."""
        deadline = time.monotonic() + (wait_s or 0.0)
        with self._cond:
            self._tares_asked += 1
            self._tare_ready = False
            if wait_s is None:
                return False
            while not self._tare_ready:
                left = deadline - time.monotonic()
                if left <= 0 or not self._thread.is_alive():
                    return False
                self._cond.wait(left)
            return True

    def stop(self) -> None:
        """End the thread and wait for it (idempotent)."""
        self._stopping.set()
        if self._thread is not threading.current_thread():
            self._thread.join(self._timeout_s + 5.0)
            if self._thread.is_alive():
                raise OptiTacError(f"the background reader {self._thread.name} did not stop within "
                                   f"{self._timeout_s + 5.0:.1f} s (its camera does not return)")
        with self._cond:
            if not self._taken:  # the newest, never returned: it will not be
                self._taken = True
                self.unread += 1
        log.debug("background reader %s stopped: %d readings, %d returned, %d unread", self._thread.name,
                  self.made, self.returned, self.unread)
