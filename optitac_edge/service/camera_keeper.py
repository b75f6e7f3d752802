"""The camera of a frame loop, kept open: a failed camera is closed and reopened with exponential backoff.

:class:`CameraKeeper` holds the camera the loop reads (the caller's, or one its
factory opened), counts read failures, closes a failed camera and reopens it
from the factory after :class:`~optitac_edge.io.backoff.Backoff`'s waits (on the
loop's clock), refusing a reopened camera that delivers other frames.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from optitac_edge.errors import FrameMismatchError
from optitac_edge.io.backoff import Backoff
from optitac_edge.io.cameras.base import Camera, CapturedFrame
from optitac_edge.io.clock import Clock
from optitac_edge.service.stats import ServiceStats, camera_failed

#: The frame loop's logger: these lines are the loop's, and keep its name in the journal.
log = logging.getLogger("optitac_edge.service.loop")

#: First wait before reopening a failed camera, s (doubles per failed attempt).
REOPEN_BACKOFF_S = 0.05
#: Longest wait between camera reopen attempts, s (also capped at a quarter of the frame gap).
REOPEN_BACKOFF_MAX_S = 1.0
#: Longest wait of the loop while it has no camera or the camera failed, s (it kicks the watchdog between).
IDLE_WAIT_S = 0.05
#: The loop has caught up with its camera at the first read that waited this part of a frame period for its
#: frame (no backlog left), or this long after its first read, s: frames lost before are counted apart.
CAUGHT_UP_WAIT_PERIODS = 0.25
CAUGHT_UP_AFTER_S = 1.0


class CameraKeeper:
    """The loop's camera: read, failure, close and reopen.

    Parameters
    ----------
    camera : Camera or None
        Opened by the caller (it stays the caller's to close); None: the factory opens the first one.
    factory : callable, optional
        Opens the camera again after a failure (the keeper then closes the cameras it opened itself).
    clock : Clock
    stats : ServiceStats
        Where reads that fail and reopens are counted.
    max_gap_s : float
        The loop's longest frame gap: the backoff waits at most a quarter of it.
    """

    def __init__(self, camera: Camera | None, factory: Callable[[], Camera] | None, clock: Clock,
                 stats: ServiceStats, max_gap_s: float) -> None:
        if camera is None:
            if factory is None:
                raise ValueError("Service needs a camera or a camera_factory")
            camera = factory()
            self._owned: Camera | None = camera
        else:
            self._owned = None
        self.camera: Camera | None = camera
        self.factory = factory
        self.clock = clock
        self.stats = stats
        self.frame_shape = camera.frame_shape
        self.pixel_format = camera.pixel_format
        self._backoff = Backoff(REOPEN_BACKOFF_S, min(REOPEN_BACKOFF_MAX_S, max_gap_s / 4))
        self._reopen_at_ns = 0
        #: The loop has read its camera's backlog (see CAUGHT_UP_WAIT_PERIODS); the gaps before are counted in
        #: ``stats.frames_dropped_before_loop``: the camera streamed while the bundles were made.
        self._caught_up = False
        self._first_read_ns: int | None = None

    def read(self, stop: threading.Event, timeout_s: float) -> tuple[CapturedFrame | None, int, bool]:
        """(The next frame, or None at the end of a finite source; frames the camera dropped before it; whether
        a frame was read). A read that fails is counted (``failed`` is True and the frame None)."""
        camera = self.camera
        assert camera is not None
        dropped = camera.frames_dropped  # the camera counts its sequence gaps
        asked_ns = self.clock.monotonic_ns()
        try:
            captured = camera.read(timeout_s)
        except Exception as exc:  # noqa: BLE001 - one bad read never ends the service
            self._failed(stop, exc)
            return None, 0, False
        dropped = camera.frames_dropped - dropped
        if not self._caught_up:
            self._catch_up(camera, asked_ns, dropped)
            return captured, 0, True
        return captured, dropped, True

    def _catch_up(self, camera: Camera, asked_ns: int, dropped: int) -> None:
        """Count a gap before the loop caught up apart; caught up once a read waited for its frame."""
        self.stats.frames_dropped_before_loop += dropped
        now_ns = self.clock.monotonic_ns()
        if self._first_read_ns is None:
            self._first_read_ns = asked_ns
        waited_periods = (now_ns - asked_ns) * camera.fps / 1e9
        self._caught_up = (waited_periods >= CAUGHT_UP_WAIT_PERIODS
                          or now_ns - self._first_read_ns >= CAUGHT_UP_AFTER_S * 1e9)

    def _failed(self, stop: threading.Event, exc: Exception) -> None:
        """Count a failed read; close the camera for a reopen (or, without a factory, wait a little)."""
        camera_failed(self.stats, exc)
        if self.factory is not None:
            self._close_camera()
            self._reopen_at_ns = self.clock.monotonic_ns() + int(self._backoff.next() * 1e9)
        else:
            self.clock.wait(stop, min(self._backoff.delay, IDLE_WAIT_S))

    def reopen_step(self, stop: threading.Event, now_ns: int) -> None:
        """Without a camera: reopen it when its time has come, else wait a little (at most IDLE_WAIT_S)."""
        if now_ns >= self._reopen_at_ns:
            if self._try_reopen():
                self._backoff.reset()
                return
            self._reopen_at_ns = now_ns + int(self._backoff.next() * 1e9)
        self.clock.wait(stop, min(max(self._reopen_at_ns - now_ns, 0) / 1e9, IDLE_WAIT_S))

    def _try_reopen(self) -> bool:
        assert self.factory is not None
        st = self.stats
        try:
            cam = self.factory()
            if cam.frame_shape != self.frame_shape or cam.pixel_format != self.pixel_format:
                cam.close()
                raise FrameMismatchError(f"reopened camera delivers {cam.pixel_format} {cam.frame_shape}, "
                                         f"expected {self.pixel_format} {self.frame_shape}")
        except Exception as exc:  # noqa: BLE001 - device still gone: try again later
            st.reopen_failures += 1
            if st.reopen_failures == 1 or st.reopen_failures % 20 == 0:
                log.warning("camera reopen failed (%d): %s", st.reopen_failures, exc)
            return False
        self.camera = self._owned = cam
        st.reopens += 1
        log.info("camera reopened (%d)", st.reopens)
        return True

    def _close_camera(self) -> None:
        cam, self.camera = self.camera, None
        if cam is self._owned:
            self._owned = None
        if cam is not None and self.factory is not None:
            # the failed device is released before it is reopened (close() is idempotent,
            # so the caller's own close of the camera it passed in stays harmless)
            try:
                cam.close()
            except Exception as exc:  # noqa: BLE001 - a failing close must not stop the reopen
                log.warning("closing the failed camera: %s", exc)

    def close(self) -> None:
        """Close the camera the keeper opened itself (idempotent)."""
        if self._owned is not None:
            self._close_camera()
