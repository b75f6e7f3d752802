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
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from optitac_edge.config import BoardConfig, CameraConfig, SensorConfig
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.frame_result import FrameResult
from optitac_edge.core.pipeline import Pipeline, single_threaded_opencv
from optitac_edge.errors import CameraError, FrameMismatchError, OptiTacError
from optitac_edge.io.backoff import Backoff
from optitac_edge.io.cameras.base import Camera, CapturedFrame
from optitac_edge.io.clock import SYSTEM_CLOCK, Clock
from optitac_edge.io.protocol.messages import TEMP_UNKNOWN, Command, CommandType, SensorState, StatusMessage
from optitac_edge.io.protocol.outbox import LinkState
from optitac_edge.io.sdnotify import Notifier
from optitac_edge.io.thermal import cpu_temperature_c
from optitac_edge.io.transports.base import Transport
from optitac_edge.service.channel import SensorChannel

if TYPE_CHECKING:
    from optitac_edge.service.network import NetworkOutput

log = logging.getLogger(__name__)

#: First wait before reopening a failed camera, s (doubles per failed attempt).
REOPEN_BACKOFF_S = 0.05
#: Longest wait between camera reopen attempts, s (also capped at a quarter of the frame gap).
REOPEN_BACKOFF_MAX_S = 1.0
#: Longest wait of the loop while it has no camera or the camera failed, s (it kicks the watchdog between).
IDLE_WAIT_S = 0.05
#: GIL switch interval while the service runs, s (the interpreter's default is 5 ms).
SWITCH_INTERVAL_S = 0.0005
OnResult = Callable[[FrameResult, "ServiceStats"], None]


class ServiceStalled(OptiTacError):
    """No good frame for ``watchdog.max_frame_gap_s``: the service exits so systemd restarts it."""


@dataclass
class ServiceStats:
    """Counters of one run.

    ``camera_errors`` counts every frame fault (read errors and timeouts, wrong
    frames, dark and saturated frames); the other counters split it by kind.
    With several sensors on the camera, ``frames`` counts camera frames some
    sensor processed, ``contacts`` every sensor's frames with a contact, and a
    dark or saturated patch counts once per sensor it hides.
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
    light_changes: int = 0  # common-mode changes of the light (LED dimming), not reported as contacts
    baseline_raises: int = 0  # fibers brighter than their baseline (taken over a press): raised to their light
    processing_errors: int = 0  # frames the pipeline failed on (a bug): counted, flagged, baseline re-taken
    protocol_refused: int = 0  # SET_PROTOCOL for a version the link cannot speak: ignored
    reopens: int = 0  # successful camera reopens
    reopen_failures: int = 0
    commands: dict[str, int] = field(default_factory=dict)
    started_ns: int = 0
    #: The frame rate over the last status period (:meth:`measure_rate`), frames/s.
    recent_fps: float = 0.0
    _rate_mark: tuple[int, int] | None = None

    def fps(self, now_ns: int) -> float:
        """Frames per second since the start (the run's summary)."""
        elapsed = (now_ns - self.started_ns) / 1e9
        return self.frames / elapsed if elapsed > 0 else 0.0

    def measure_rate(self, now_ns: int) -> float:
        """The frame rate since the previous call (or the start), kept as :attr:`recent_fps`: what STATUS says.

        The average since the start over-read for a long time after it (the frames queued while the
        service started come at once: 85 fps, then 62, on a 60-fps camera).
        """
        since_ns, since_frames = self._rate_mark or (self.started_ns, 0)
        if now_ns - since_ns >= 200_000_000 or self._rate_mark is None:
            span = (now_ns - since_ns) / 1e9
            self.recent_fps = (self.frames - since_frames) / span if span > 0 else 0.0
            self._rate_mark = (now_ns, self.frames)
        return self.recent_fps


class _CameraEnded(Exception):
    """The camera is a finite source (a recording) and has no more frames."""



class Service:
    """Runs the frame loop of one camera: every sensor the camera reads, one transport.

    ``camera`` is opened by the caller (it stays the caller's to close); with
    ``camera_factory`` the service can also reopen the camera after a failure
    (it then closes the cameras it opened itself). ``camera`` may be None when
    a factory is given: the factory opens the first one. Every time the loop
    reads or waits goes through ``clock`` (a
    :class:`~optitac_edge.io.clock.VirtualClock` makes a run deterministic).

    ``sensors`` lists the camera's sensors with their bundles (default: the
    board's ``[sensor]`` with ``bundle``); ``camera_config`` is the camera's
    section (default: the board's ``[camera]``). A board with several cameras
    runs one service per camera (:mod:`optitac_edge.service.session`): the
    first is the lead, which alone polls the MCU's commands (passing each to
    its :attr:`peers`), kicks systemd's watchdog while every peer's loop is
    alive, and says READY once each has processed a frame.
    """

    def __init__(self, config: BoardConfig, bundle: CalibrationBundle | None, camera: Camera | None,
                 transport: Transport, notifier: Notifier | None = None, *,
                 camera_factory: Callable[[], Camera] | None = None, clock: Clock = SYSTEM_CLOCK,
                 sensors: Sequence[tuple[SensorConfig, CalibrationBundle]] | None = None,
                 camera_config: CameraConfig | None = None, camera_name: str | None = None) -> None:
        if camera is None:
            if camera_factory is None:
                raise ValueError("Service needs a camera or a camera_factory")
            camera = camera_factory()
            self._owned: Camera | None = camera
        else:
            self._owned = None
        if sensors is None:
            if bundle is None:
                raise ValueError("Service needs a bundle or sensors")
            sensors = [(config.sensor, bundle)]
        for sensor, b in sensors:
            b.fibers.check_frame_shape(camera.frame_shape, camera.pixel_format)
        self.config = config
        self.camera_config = camera_config or config.camera
        #: The camera's name in the board config (for logs).
        self.camera_name = camera_name or config.sensor.camera
        self.clock = clock
        self.camera: Camera | None = camera
        self.camera_factory = camera_factory
        self.transport = transport
        self.notifier = notifier or Notifier(env={})
        #: One per sensor the camera reads, in the board's order.
        self.channels = [SensorChannel(sensor.id, sensor.name, b, camera.frame_shape) for sensor, b in sensors]
        #: The services of the board's other cameras (this one is the lead when it has any).
        self.peers: list[Service] = []
        #: This service is one of a lead's peers: it takes commands from its inbox and leaves systemd alone.
        self.is_peer = False
        #: The live view (``run --view``): ``observe(frame, t_ns, pipeline, stats)`` after each frame, never blocking.
        self.view: Any = None
        #: The network publisher's frame-loop side (``[publish.NAME]``): ``offer_*`` copy and return, never blocking.
        self.network: NetworkOutput | None = None
        #: Protocol, streaming and rate divider, as the MCU's commands set them.
        self.link = LinkState(rate_divider=config.link.rate_divider, delivers=transport.delivers,
                              v2_alongside_v1=transport.v2_alongside_v1)
        self.stats = ServiceStats()
        self._inbox: deque[Command] = deque()
        self._pixel_format = camera.pixel_format
        self._frame_shape = camera.frame_shape
        #: The bundle could not be saved (the service runs on it from memory): STATUS bit5.
        self.calibration_unsaved = False
        gap_s = config.watchdog.max_frame_gap_s
        self._backoff = Backoff(REOPEN_BACKOFF_S, min(REOPEN_BACKOFF_MAX_S, gap_s / 4))
        self._max_gap_ns = int(gap_s * 1e9)
        self._status_period_ns = int(config.status.period_s * 1e9)
        self._reopen_at_ns = 0
        self._last_good_ns = 0
        #: When the loop last went round (peers: what the lead's watchdog kick checks).
        self.heartbeat_ns = 0
        self._next_status_ns = 0
        self._ready = False
        #: The lead told systemd READY.
        self.notifier_ready = False

    @property
    def pipeline(self) -> Pipeline:
        """The first sensor's pipeline (the only one on a one-sensor camera)."""
        return self.channels[0].pipeline

    @property
    def bundle(self) -> CalibrationBundle:
        """The first sensor's bundle."""
        return self.channels[0].bundle

    # -- commands ----------------------------------------------------------------------------

    def handle(self, command: Command) -> None:
        """Act on one validated command from the MCU (already acknowledged by the transport).

        Commands carry no sensor id: each applies to every sensor of the board
        (the lead passes it on to its peers, which act on it in their own loop).
        """
        name = command.type.name
        self.stats.commands[name] = self.stats.commands.get(name, 0) + 1
        for peer in self.peers:
            peer.post(command)
        if command.type == CommandType.TARE:
            for ch in self.channels:
                ch.pipeline.reset_baseline()
        elif command.type == CommandType.STREAM:
            self.link.streaming = command.stream_on
            self.link.rate_divider = max(int(command.rate_divider), 1)
        elif command.type == CommandType.SET_THRESHOLD:
            for ch in self.channels:
                ch.pipeline.set_contact_level(command.threshold_relative)
        elif command.type == CommandType.SET_PROTOCOL:
            if command.version in self.transport.protocols:
                if command.version != self.link.protocol and not self.is_peer:
                    log.info("the MCU switched to protocol v%d", command.version)
                self.link.protocol = command.version
                for ch in self.channels:
                    ch.outbox.new_session()  # every contact is news to the MCU
            else:
                self.stats.protocol_refused += 1
                if not self.is_peer:  # the lead says it once for the board
                        log.warning("SET_PROTOCOL %d ignored: this link speaks %s", command.version,
                                ", ".join(f"v{v}" for v in self.transport.protocols))

    def post(self, command: Command) -> None:
        """From the lead's thread: a command for this service's loop (acted on before its next frame)."""
        self._inbox.append(command)

    # -- status ------------------------------------------------------------------------------

    def sensor_state(self, index: int = 0) -> SensorState:
        """The flags of sensor ``index`` of this camera for its STATUS (those since its last STATUS)."""
        ch = self.channels[index]
        return SensorState(streaming=self.link.streaming, baseline_ready=ch.pipeline.baseline_ready,
                           degraded=ch.degraded, camera_fault=ch.fault_since_status or self.camera is None,
                           light_change=ch.light_since_status, calibration_unsaved=self.calibration_unsaved,
                           protocol_v2=self.link.protocol == 2)

    def status_message(self, now_ns: int, index: int = 0, state: SensorState | None = None) -> StatusMessage:
        """The STATUS of sensor ``index`` of this camera (its flags since its last STATUS, then cleared)."""
        ch, st = self.channels[index], self.stats
        s = ch.status
        s.t_us = now_ns // 1000
        s.fps_x10 = round(st.recent_fps * 10)
        s.frames_dropped = st.frames_dropped
        s.camera_errors = st.camera_errors
        c = self.transport.counters
        s.link_errors = c.send_errors + c.rx_errors
        temp = cpu_temperature_c()
        s.cpu_temp_c_x10 = TEMP_UNKNOWN if temp is None else round(temp * 10)
        s.state = (self.sensor_state(index) if state is None else state).bits
        ch.fault_since_status = ch.light_since_status = False
        return s

    def send_status(self, now_ns: int) -> None:
        """A STATUS for every sensor of the camera, with the frame rate of the last status period."""
        self.stats.measure_rate(now_ns)
        for k, ch in enumerate(self.channels):
            state = self.sensor_state(k)
            status = self.status_message(now_ns, k, state)
            self.transport.send_status(status)
            if self.network is not None:
                self.network.offer_status(ch.sensor_id, status, state, ch.frames, ch.contacts,
                                          self.stats.recent_fps, self.link.protocol)

    def _flag_fault(self) -> None:
        for ch in self.channels:
            ch.fault_since_status = True

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

    def _reopen_step(self, stop: threading.Event, now_ns: int) -> None:
        """Without a camera: reopen it when its time has come, else wait a little (at most IDLE_WAIT_S)."""
        if now_ns >= self._reopen_at_ns:
            if self._try_reopen():
                self._backoff.reset()
                return
            self._reopen_at_ns = now_ns + int(self._backoff.next() * 1e9)
        self.clock.wait(stop, min(max(self._reopen_at_ns - now_ns, 0) / 1e9, IDLE_WAIT_S))

    def _camera_failed(self, stop: threading.Event, exc: Exception) -> None:
        """Count a failed read; close the camera for a reopen (or, without a factory, wait a little)."""
        st = self.stats
        st.camera_errors += 1
        if isinstance(exc, CameraError):
            st.read_errors += 1
        else:
            st.unexpected_errors += 1
        self._flag_fault()
        if st.camera_errors == 1 or st.camera_errors % 100 == 0:
            log.warning("camera error %d: %s: %s", st.camera_errors, type(exc).__name__, exc)
        if self.camera_factory is not None:
            self._close_camera()
            self._reopen_at_ns = self.clock.monotonic_ns() + int(self._backoff.next() * 1e9)
        else:
            self.clock.wait(stop, min(self._backoff.delay, IDLE_WAIT_S))

    def replace_pipeline(self, pipeline: Pipeline) -> None:
        """The first sensor uses ``pipeline`` from the next frame (a bundle re-oriented from the view; built off
        the frame thread)."""
        self.channels[0].replace_pipeline(pipeline)

    def close(self) -> None:
        """Close the camera the service opened itself (idempotent)."""
        if self._owned is not None:
            self._close_camera()

    # -- the loop ----------------------------------------------------------------------------

    def run(self, stop: threading.Event, duration_s: float | None = None,
            on_result: OnResult | None = None) -> ServiceStats:
        """Process frames until ``stop`` is set, ``duration_s`` passes or a finite source ends.

        Raises
        ------
        ServiceStalled
            No good frame for ``watchdog.max_frame_gap_s`` (the watchdog is no longer kicked).
        """
        # Everything alive now (modules, bundle, buffers: ~30 000 objects) lives as long as the
        # service: moved out of the collector's reach, a full collection takes microseconds,
        # not the ~6 ms (more than a frame at 240 fps) it takes scanning them all.
        gc.collect()
        gc.freeze()
        # The camera and link threads hand frames and packets to this loop; with the
        # interpreter's default 5 ms switch interval a packet can wait that long for the GIL.
        switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        try:
            with single_threaded_opencv():
                return self._run(stop, duration_s, on_result)
        finally:
            sys.setswitchinterval(switch_interval)

    def _run(self, stop: threading.Event, duration_s: float | None, on_result: OnResult | None) -> ServiceStats:
        st = self.stats
        st.started_ns = self._last_good_ns = self.heartbeat_ns = self.clock.monotonic_ns()
        end_ns = None if duration_s is None else st.started_ns + int(duration_s * 1e9)
        self._next_status_ns = st.started_ns + self._status_period_ns
        try:
            while not stop.is_set():
                now_ns = self.heartbeat_ns = self.clock.monotonic_ns()
                if end_ns is not None and now_ns >= end_ns:
                    break
                self._check_frame_gap(now_ns)
                try:
                    result = self._step(stop, now_ns)
                except _CameraEnded:
                    break
                self._after_step(result, on_result)
        finally:
            self._shut_down()
        log.info("camera %s stopped after %d frames (%d contacts, %d dropped, %d camera faults, %d reopens, "
                 "%d processing errors, %d light changes, %d baseline raises)", self.camera_name, st.frames,
                 st.contacts, st.frames_dropped, st.camera_errors, st.reopens, st.processing_errors,
                 st.light_changes, st.baseline_raises)
        return st

    def _check_frame_gap(self, now_ns: int) -> None:
        if now_ns - self._last_good_ns > self._max_gap_ns:
            raise ServiceStalled(f"no good camera frame for {(now_ns - self._last_good_ns) / 1e9:.1f} s "
                                 f"({self.stats.camera_errors} camera faults); exiting so systemd restarts")

    def _step(self, stop: threading.Event, now_ns: int) -> FrameResult | None:
        """One pass: reopen the camera or read a frame and process it; the first sensor's result, or None.

        Raises :class:`_CameraEnded` when a finite source has no more frames.
        """
        camera = self.camera
        if camera is None:  # reopening after a failure
            self._reopen_step(stop, now_ns)
            return None
        dropped = camera.frames_dropped  # the camera counts its sequence gaps
        try:
            captured = camera.read(self.camera_config.timeout_s)
        except Exception as exc:  # noqa: BLE001 - one bad read never ends the service
            self._camera_failed(stop, exc)
            return None
        if captured is None:
            raise _CameraEnded
        self.stats.frames_dropped += camera.frames_dropped - dropped
        result, device_fault = self._process(captured)
        if self.view is not None:  # the live view copies what it needs when an update is due; never waits
            self.view.observe(captured.frame, captured.t_ns, self.pipeline, self.stats)
        if not device_fault:  # a camera delivering wrong frames counts towards the frame gap
            self._last_good_ns = self.clock.monotonic_ns()
        return result

    def _after_step(self, result: FrameResult | None, on_result: OnResult | None) -> None:
        """READY once, the watchdog kick, the MCU's commands, the caller's hook, STATUS when due."""
        if result is not None and not self._ready:
            self._ready = True
        if not self.is_peer:
            self._tell_systemd()
            for command in self.transport.poll_commands():
                self.handle(command)
        while self._inbox:
            self.handle(self._inbox.popleft())
        if result is not None and on_result is not None:
            on_result(result, self.stats)
        now_ns = self.clock.monotonic_ns()
        if now_ns >= self._next_status_ns:
            self._next_status_ns = now_ns + self._status_period_ns
            self.send_status(now_ns)

    def _tell_systemd(self) -> None:
        """The lead: READY once every camera processed a frame; the watchdog kick while every loop goes round."""
        if self._ready and not self.notifier_ready and all(p._ready for p in self.peers):
            self.notifier_ready = True
            self.notifier.ready("processing frames")
            log.info("first frame processed; %s", "streaming to the MCU" if self.transport.delivers
                     else "no link to an MCU: nothing is sent")
        if self.config.watchdog.enabled:
            now_ns = self.clock.monotonic_ns()
            # from the loop itself: a stuck loop (or a peer's, stuck in its camera driver) stops kicking
            if all(now_ns - p.heartbeat_ns <= self._max_gap_ns for p in self.peers):
                self.notifier.watchdog(now_ns / 1e9)

    def _shut_down(self) -> None:
        try:  # a last STATUS: the MCU sees the final counters
            self.send_status(self.clock.monotonic_ns())
        except Exception as exc:  # noqa: BLE001 - shutting down anyway
            log.warning("final status not sent: %s", exc)
        if not self.is_peer:
            self.notifier.stopping()
        self.close()

    def _process(self, captured: CapturedFrame) -> tuple[FrameResult | None, bool]:
        """Check and process one captured frame for every sensor: (the first sensor's result, None when no
        sensor processed the frame; a device fault)."""
        st = self.stats
        first: FrameResult | None = None
        processed = device_fault = False
        send = self.link.due(st.frames + 1)
        for ch in self.channels:
            result, fault = self._process_sensor(ch, captured, send)
            device_fault |= fault is not None
            if fault == "bad":
                break  # a frame of the wrong shape or type is wrong for every sensor: counted once
            if result is not None and not processed:
                processed, first = True, result
        if processed:
            st.frames += 1
            st.sent += int(send)
        return first, device_fault

    def _process_sensor(self, ch: SensorChannel, captured: CapturedFrame,
                        send: bool) -> tuple[FrameResult | None, str | None]:
        """One sensor's part of a frame: the frame check, the pipeline, the outbox's messages sent. Returns
        its result (None: skipped) and the device fault: None, "bad" (a wrong frame) or "failed" (the
        pipeline failed)."""
        try:
            why = ch.frame_check(captured.frame)
        except Exception:  # noqa: BLE001 - anything odd about the frame object: a bad frame
            why = "bad"
        if why is not None:
            self._frame_skipped(ch, why)
            return None, "bad" if why == "bad" else None
        try:
            result = ch.pipeline.process(captured.frame, captured.t_ns, ch.frame_check.saturated)
        except Exception as exc:  # noqa: BLE001 - a per-frame failure never ends the service
            self._processing_failed(ch, exc)
            return None, "failed"  # a loop failing on every frame counts towards the frame gap
        self._count(ch, result)
        if self.network is not None:
            self.network.offer_frame(ch.sensor_id, result, ch.degraded, ch.pipeline.signal, captured.frame,
                                     ch.pipeline.surface)
        for message in ch.outbox.update(result, self.link, send, self.clock.monotonic_ns()):
            self.transport.send(message)
        return result, None

    def _count(self, ch: SensorChannel, result: FrameResult) -> None:
        """The sensor's counters and flags from its frame (and a log line on the first and every 100th event)."""
        st = self.stats
        contact = result.n_contacts > 0
        ch.frames += 1
        ch.contacts += contact
        st.contacts += contact
        st.saturated_sent += result.saturated
        if result.light_changed:
            self._light_changed(ch)
        if result.baseline_raised:
            self._baseline_raised(ch, result.raised_fibers)

    def _light_changed(self, ch: SensorChannel) -> None:
        st = self.stats
        st.light_changes += 1
        ch.light_since_status = True
        if st.light_changes == 1 or st.light_changes % 100 == 0:
            log.warning("common-mode change of the light %d (LED dimming or brightening to %.3f of the "
                        "baseline, sensor %d): not a contact", st.light_changes, ch.pipeline.gain, ch.sensor_id)

    def _baseline_raised(self, ch: SensorChannel, fibers: int) -> None:
        st = self.stats
        st.baseline_raises += 1
        if st.baseline_raises == 1 or st.baseline_raises % 100 == 0:
            log.warning("baseline raised %d (sensor %d): %d fibers stayed brighter than their baseline, which no "
                        "press can make: it was taken while the skin was pressed there (a start or a tare during "
                        "a grasp); their baseline is now their light", st.baseline_raises, ch.sensor_id, fibers)

    def _processing_failed(self, ch: SensorChannel, exc: Exception) -> None:
        """Count a frame the pipeline failed on, flag it, and start its state afresh (a new baseline)."""
        st = self.stats
        st.processing_errors += 1
        ch.fault_since_status = True
        if st.processing_errors == 1 or st.processing_errors % 100 == 0:
            log.error("processing error %d (sensor %d): %s: %s; the baseline is taken again", st.processing_errors,
                      ch.sensor_id, type(exc).__name__, exc)
        ch.pipeline.reset_baseline()

    def _frame_skipped(self, ch: SensorChannel, why: str) -> None:
        st = self.stats
        st.camera_errors += 1
        ch.fault_since_status = True
        if why == "bad":
            st.bad_frames += 1
        elif why == "dark":
            st.dark_frames += 1
        else:
            st.saturated_frames += 1
        if st.camera_errors == 1 or st.camera_errors % 100 == 0:
            log.warning("camera fault %d: %s frame skipped (sensor %d)", st.camera_errors, why, ch.sensor_id)
