"""The service: camera -> pipeline -> link to the MCU, the one loop that does I/O.

Everything it computes comes from :class:`~optitac_edge.core.pipeline.Pipeline`
(pure computation on a frame and its timestamp); this module reads the
camera, sends the messages, answers the MCU's commands, sends STATUS about
once a second and keeps systemd informed (READY after the first processed
frame, WATCHDOG from the frame loop itself). It never logs per frame.

Faults (docs/reliability.md): a frame of the wrong shape or dtype, an all-dark
or saturated frame is skipped and counted; a camera error or timeout is
counted and the camera is closed and reopened with exponential backoff (when
the service has a camera factory); STATUS flags all of it (state bit3). When
no good frame arrived for ``watchdog.max_frame_gap_s`` the loop stops kicking
systemd's watchdog and :meth:`Service.run` raises :class:`ServiceStalled`, so
the process exits non-zero and systemd restarts it. A loop stuck inside a
driver call stops kicking too: systemd's watchdog (``WatchdogSec``) restarts it.
"""

from __future__ import annotations

import gc
import logging
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.contact import ContactEstimate
from optitac_edge.errors import CameraError, FrameMismatchError, OptiTacError
from optitac_edge.io.cameras.base import Camera
from optitac_edge.io.protocol.messages import Command, CommandType, ContactMessage, StatusMessage
from optitac_edge.io.sdnotify import Notifier
from optitac_edge.io.thermal import cpu_temperature_c
from optitac_edge.io.transports.base import Transport
from optitac_edge.service.board_config import BoardConfig

log = logging.getLogger(__name__)

#: First wait before reopening a failed camera, s (doubles per failed attempt).
REOPEN_BACKOFF_S = 0.05
#: Longest wait between camera reopen attempts, s (also capped at a quarter of the frame gap).
REOPEN_BACKOFF_MAX_S = 1.0
#: Fewer than DARK_FRACTION of the sampled fiber centres above this gray level: the frame is dark.
DARK_LEVEL = 8
DARK_FRACTION = 0.1
#: Gray level counted as saturated (full scale).
SATURATED_LEVEL = 255
#: More than this fraction of the live fibers' centres saturated: the frame is skipped.
SATURATED_FRACTION = 0.5
#: GIL switch interval while the service runs, s (the interpreter's default is 5 ms).
SWITCH_INTERVAL_S = 0.0005
#: SET_THRESHOLD unit: the contact-on level in 1e-4 of the rest light (relative signal).
THRESHOLD_UNIT = 1e-4


class ServiceStalled(OptiTacError):
    """No good frame for ``watchdog.max_frame_gap_s``: the service exits so systemd restarts it."""


@dataclass
class ServiceStats:
    """Counters of one run.

    ``camera_errors`` counts every frame fault (read errors and timeouts, wrong
    frames, dark and saturated frames); the other counters split it by kind.
    """

    frames: int = 0
    contacts: int = 0
    sent: int = 0
    frames_dropped: int = 0
    camera_errors: int = 0
    read_errors: int = 0  # CameraError from read(): timeouts, device gone, driver errors
    unexpected_errors: int = 0  # any other exception from the camera (a backend bug): counted like read_errors
    bad_frames: int = 0  # wrong shape or dtype
    dark_frames: int = 0
    saturated_frames: int = 0  # skipped: most fibers at full scale
    saturated_sent: int = 0  # processed frames with some fiber at full scale (SATURATED flag)
    reopens: int = 0  # successful camera reopens
    reopen_failures: int = 0
    commands: dict[str, int] = field(default_factory=dict)
    started_ns: int = 0

    def fps(self, now_ns: int) -> float:
        elapsed = (now_ns - self.started_ns) / 1e9
        return self.frames / elapsed if elapsed > 0 else 0.0


class Service:
    """Runs the frame loop with one camera, one pipeline and one transport.

    ``camera`` is opened by the caller (it stays the caller's to close); with
    ``camera_factory`` the service can also reopen the camera after a failure
    (it then closes the cameras it opened itself). ``camera`` may be None when
    a factory is given: the factory opens the first one.
    """

    def __init__(self, config: BoardConfig, bundle: CalibrationBundle, camera: Camera | None,
                 transport: Transport, notifier: Notifier | None = None, *,
                 camera_factory: Callable[[], Camera] | None = None) -> None:
        from optitac_edge.core.pipeline import Pipeline

        if camera is None:
            if camera_factory is None:
                raise ValueError("Service needs a camera or a camera_factory")
            camera = camera_factory()
            self._owned: Camera | None = camera
        else:
            self._owned = None
        bundle.fibers.check_frame(np.zeros(camera.frame_shape, np.uint8), camera.pixel_format)
        self.config = config
        self.bundle = bundle
        self.camera: Camera | None = camera
        self.camera_factory = camera_factory
        self.transport = transport
        self.notifier = notifier or Notifier(env={})
        self.pipeline = Pipeline(bundle)
        self.streaming = True
        self.rate_divider = config.link.rate_divider
        self.stats = ServiceStats()
        self._message = ContactMessage(sensor_id=config.sensor.id)
        self._status = StatusMessage(sensor_id=config.sensor.id,
                                     calibration_id=int(bundle.calibration_id[:8] or "0", 16))
        self._degraded = bool(bundle.fibers.dead.any())
        self._fault_since_status = False
        self._device_fault = False
        #: The last processed frame had a live fiber centre at full scale.
        self.saturated = False
        # Cheap image check: one pixel (the centre) of every live fiber, luminance plane.
        t = bundle.fibers
        col = np.clip(np.rint(t.centroid_px[:, 0]), 0, t.width - 1).astype(np.intp)
        row = np.clip(np.rint(t.centroid_px[:, 1]), 0, t.height - 1).astype(np.intp)
        live = ~t.dead if (~t.dead).any() else np.ones_like(t.dead)
        self._probe = (row * t.width + col)[live]
        if t.pixel_format == "rgb":  # the three bytes of each probed pixel
            self._probe = (self._probe[:, None] * 3 + np.arange(3)).ravel()
        self._probed = np.zeros(self._probe.size, dtype=np.uint8)
        self._probe_flags = np.zeros(self._probe.size, dtype=bool)
        self._n_probes = int(live.sum())
        self._pixel_format = t.pixel_format
        self._frame_shape = camera.frame_shape

    # -- frame checks ------------------------------------------------------------------------

    def check_frame(self, frame: Any) -> str | None:
        """Why ``frame`` must be skipped (``"bad"``, ``"dark"``, ``"saturated"``), or None.

        Also sets ``self.saturated`` when some live fiber centre is at full scale
        (any channel for RGB). Costs one gather of a pixel per fiber into a
        preallocated buffer and two counts.
        """
        self.saturated = False
        if (not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.shape != self._frame_shape):
            return "bad"
        values, flags = self._probed, self._probe_flags
        frame.reshape(-1).take(self._probe, out=values, mode="clip")
        rgb = self._pixel_format == "rgb"
        # a pixel is saturated if any of its channels is; bright if its largest channel is
        np.greater_equal(values, SATURATED_LEVEL, out=flags)
        n_sat = int(np.count_nonzero(flags.reshape(-1, 3).any(axis=1))) if rgb else int(np.count_nonzero(flags))
        if n_sat > SATURATED_FRACTION * self._n_probes:
            return "saturated"
        np.greater(values, DARK_LEVEL, out=flags)
        n_lit = int(np.count_nonzero(flags.reshape(-1, 3).any(axis=1))) if rgb else int(np.count_nonzero(flags))
        if n_lit < DARK_FRACTION * self._n_probes:
            return "dark"
        self.saturated = n_sat > 0
        return None

    # -- commands ----------------------------------------------------------------------------

    def handle(self, command: Command) -> None:
        """Act on one validated command from the MCU (already acknowledged by the transport)."""
        name = command.type.name
        self.stats.commands[name] = self.stats.commands.get(name, 0) + 1
        if command.type == CommandType.TARE:
            self.pipeline.reset_baseline()
        elif command.type == CommandType.STREAM:
            self.streaming = command.stream_on
            self.rate_divider = max(int(command.rate_divider), 1)
        elif command.type == CommandType.SET_THRESHOLD:
            self.pipeline.set_contact_level(command.threshold * THRESHOLD_UNIT)

    # -- status ------------------------------------------------------------------------------

    def status_message(self, now_ns: int) -> StatusMessage:
        s, st = self._status, self.stats
        s.t_us = now_ns // 1000
        s.fps_x10 = round(st.fps(now_ns) * 10)
        s.frames_dropped = st.frames_dropped
        s.camera_errors = st.camera_errors
        c = self.transport.counters
        s.link_errors = c.send_errors + c.rx_errors
        temp = cpu_temperature_c()
        s.cpu_temp_c_x10 = -32768 if temp is None else round(temp * 10)
        fault = self._fault_since_status or self.camera is None
        s.state = ((1 if self.streaming else 0) | (2 if self.pipeline.baseline_ready else 0)
                   | (4 if self._degraded else 0) | (8 if fault else 0))
        self._fault_since_status = False
        return s

    # -- camera faults -----------------------------------------------------------------------

    def _close_camera(self) -> None:
        cam, self.camera = self.camera, None
        if cam is self._owned:
            self._owned = None
        if cam is not None and self.camera_factory is not None:
            # the failed device is released before it is reopened (close() is idempotent,
            # so the caller's own close of the camera it passed in stays harmless)
            try:
                cam.close()
            except Exception as exc:  # noqa: BLE001 - a failing close must not stop the reopen
                log.warning("closing the failed camera: %s", exc)

    def _try_reopen(self) -> bool:
        assert self.camera_factory is not None
        try:
            cam = self.camera_factory()
            if cam.frame_shape != self._frame_shape or cam.pixel_format != self._pixel_format:
                cam.close()
                raise FrameMismatchError(f"reopened camera delivers {cam.pixel_format} {cam.frame_shape}, "
                                         f"expected {self._pixel_format} {self._frame_shape}")
        except Exception as exc:  # noqa: BLE001 - device still gone: try again later
            self.stats.reopen_failures += 1
            if self.stats.reopen_failures == 1 or self.stats.reopen_failures % 20 == 0:
                log.warning("camera reopen failed (%d): %s", self.stats.reopen_failures, exc)
            return False
        self.camera = self._owned = cam
        self.stats.reopens += 1
        log.info("camera reopened (%d)", self.stats.reopens)
        return True

    def close(self) -> None:
        """Close the camera the service opened itself (idempotent)."""
        if self._owned is not None:
            self._close_camera()

    # -- the loop ----------------------------------------------------------------------------

    def run(self, stop: threading.Event, duration_s: float | None = None,
            on_result: Callable[[ContactEstimate, ServiceStats], None] | None = None) -> ServiceStats:
        """Process frames until ``stop`` is set, ``duration_s`` passes or a finite source ends.

        Raises
        ------
        ServiceStalled
            No good frame for ``watchdog.max_frame_gap_s`` (the watchdog is no longer kicked).
        """
        # The camera and link threads hand frames and packets to this loop; with the
        # interpreter's default 5 ms switch interval a packet can wait that long for the GIL.
        from optitac_edge.core.pipeline import single_threaded_opencv

        # Everything alive now (modules, bundle, buffers: ~30 000 objects) lives as long as the
        # service: moved out of the collector's reach, a full collection takes microseconds,
        # not the ~6 ms (more than a frame at 240 fps) it takes scanning them all.
        gc.collect()
        gc.freeze()
        switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        try:
            with single_threaded_opencv():
                return self._run(stop, duration_s, on_result)
        finally:
            sys.setswitchinterval(switch_interval)

    def _run(self, stop: threading.Event, duration_s: float | None,
             on_result: Callable[[ContactEstimate, ServiceStats], None] | None) -> ServiceStats:
        st = self.stats
        st.started_ns = time.monotonic_ns()
        end_ns = None if duration_s is None else st.started_ns + int(duration_s * 1e9)
        period_ns = int(self.config.status.period_s * 1e9)
        next_status = st.started_ns + period_ns
        timeout = self.config.camera.timeout_s
        max_gap_ns = int(self.config.watchdog.max_frame_gap_s * 1e9)
        kick = self.config.watchdog.enabled
        backoff_max = max(min(REOPEN_BACKOFF_MAX_S, self.config.watchdog.max_frame_gap_s / 4), REOPEN_BACKOFF_S)
        backoff = REOPEN_BACKOFF_S
        reopen_at = 0
        last_good_ns = st.started_ns
        ready = False
        try:
            while not stop.is_set():
                now_ns = time.monotonic_ns()
                if end_ns is not None and now_ns >= end_ns:
                    break
                if now_ns - last_good_ns > max_gap_ns:
                    raise ServiceStalled(f"no good camera frame for {(now_ns - last_good_ns) / 1e9:.1f} s "
                                         f"({st.camera_errors} camera faults); exiting so systemd restarts")
                est = None
                if self.camera is None:  # reopening after a failure
                    if now_ns >= reopen_at and self._try_reopen():
                        backoff = REOPEN_BACKOFF_S
                    else:
                        if now_ns >= reopen_at:
                            reopen_at = now_ns + int(backoff * 1e9)
                            backoff = min(backoff * 2, backoff_max)
                        stop.wait(min(max(reopen_at - now_ns, 0) / 1e9, 0.05))
                else:
                    camera = self.camera
                    dropped = camera.frames_dropped  # the camera counts its sequence gaps
                    try:
                        captured = camera.read(timeout)
                    except Exception as exc:  # noqa: BLE001 - one bad read never ends the service
                        st.camera_errors += 1
                        if isinstance(exc, CameraError):
                            st.read_errors += 1
                        else:
                            st.unexpected_errors += 1
                        self._fault_since_status = True
                        if st.camera_errors == 1 or st.camera_errors % 100 == 0:
                            log.warning("camera error %d: %s: %s", st.camera_errors, type(exc).__name__, exc)
                        if self.camera_factory is not None:
                            self._close_camera()
                            reopen_at = time.monotonic_ns() + int(backoff * 1e9)
                            backoff = min(backoff * 2, backoff_max)
                        else:
                            stop.wait(min(backoff, 0.05))
                        captured = False
                    if captured is None:
                        break
                    if captured is not False:
                        st.frames_dropped += camera.frames_dropped - dropped
                        est = self._process(captured)
                        if est is not None or not self._device_fault:
                            last_good_ns = time.monotonic_ns()
                if est is not None and not ready:
                    ready = True
                    self.notifier.ready("processing frames")
                    log.info("first frame processed; streaming to the MCU")
                if kick:
                    self.notifier.watchdog()  # from the loop itself: a stuck loop stops kicking
                for command in self.transport.poll_commands():
                    self.handle(command)
                if est is not None and on_result is not None:
                    on_result(est, st)
                now_ns = time.monotonic_ns()
                if now_ns >= next_status:
                    next_status = now_ns + period_ns
                    self.transport.send_status(self.status_message(now_ns))
        finally:
            try:  # a last STATUS: the MCU sees the final counters
                self.transport.send_status(self.status_message(time.monotonic_ns()))
            except Exception as exc:  # noqa: BLE001 - shutting down anyway
                log.warning("final status not sent: %s", exc)
            self.notifier.stopping()
            self.close()
        log.info("stopped after %d frames (%d contacts, %d dropped, %d camera faults, %d reopens)",
                 st.frames, st.contacts, st.frames_dropped, st.camera_errors, st.reopens)
        return st

    def _process(self, captured: Any) -> ContactEstimate | None:
        """Check and process one captured frame; None when it was skipped (counted)."""
        st = self.stats
        self._device_fault = False
        try:
            why = self.check_frame(captured.frame)
        except Exception:  # noqa: BLE001 - anything odd about the frame object: a bad frame
            why = "bad"
        if why is not None:
            st.camera_errors += 1
            self._fault_since_status = True
            if why == "bad":
                st.bad_frames += 1
                self._device_fault = True  # a camera delivering wrong frames counts towards the gap
            elif why == "dark":
                st.dark_frames += 1
            else:
                st.saturated_frames += 1
            if st.camera_errors == 1 or st.camera_errors % 100 == 0:
                log.warning("camera fault %d: %s frame skipped", st.camera_errors, why)
            return None
        est = self.pipeline.process(captured.frame, captured.t_ns)
        st.frames += 1
        st.contacts += int(est.contact)
        st.saturated_sent += int(self.saturated)
        if self.streaming and st.frames % self.rate_divider == 0:
            self._message.fill(est, captured.t_ns, time.monotonic_ns(), self.pipeline.calibrated,
                               saturated=self.saturated, degraded=self._degraded)
            self.transport.send_contact(self._message)
            st.sent += 1
        return est


