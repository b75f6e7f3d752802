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
from typing import TYPE_CHECKING

from optitac_edge.config import BoardConfig, CameraConfig, SensorConfig
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.frame_engine import Skip
from optitac_edge.core.frame_result import FrameResult
from optitac_edge.core.pipeline import Pipeline, single_threaded_opencv
from optitac_edge.errors import OptiTacError
from optitac_edge.io.cameras.base import Camera, CapturedFrame
from optitac_edge.io.clock import SYSTEM_CLOCK, Clock
from optitac_edge.io.protocol.messages import Command
from optitac_edge.io.protocol.outbox import LinkState
from optitac_edge.io.sdnotify import Notifier
from optitac_edge.io.startup import STARTUP
from optitac_edge.io.transports.base import Transport
from optitac_edge.service import stats as counts
from optitac_edge.service.camera_keeper import CameraKeeper
from optitac_edge.service.channel import SensorChannel
from optitac_edge.service.commands import Outcome, apply_command
from optitac_edge.service.pool import SensorPool, spare_workers
from optitac_edge.service.stage_times import StageTimes
from optitac_edge.service.stats import ServiceStats
from optitac_edge.service.status import StatusReporter

if TYPE_CHECKING:
    from optitac_edge.service.network import NetworkOutput
    from optitac_edge.service.view.live import LiveView

log = logging.getLogger(__name__)

#: GIL switch interval while the service runs, s (the interpreter's default is 5 ms).
SWITCH_INTERVAL_S = 0.0005
OnResult = Callable[[FrameResult, "ServiceStats"], None]


class ServiceStalled(OptiTacError):
    """No good frame for ``watchdog.max_frame_gap_s``: the service exits so systemd restarts it."""


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

    def __init__(self, config: BoardConfig, bundle: CalibrationBundle | None, camera: Camera | None,  # noqa: PLR0913
                 transport: Transport, notifier: Notifier | None = None, *,
                 camera_factory: Callable[[], Camera] | None = None, clock: Clock = SYSTEM_CLOCK,
                 sensors: Sequence[tuple[SensorConfig, CalibrationBundle]] | None = None,
                 camera_config: CameraConfig | None = None, camera_name: str | None = None,
                 workers: int | None = None) -> None:
        self.stats = ServiceStats()
        gap_s = config.watchdog.max_frame_gap_s
        #: The camera, reopened after a failure when there is a factory.
        self.keeper = CameraKeeper(camera, camera_factory, clock, self.stats, gap_s)
        camera = self.keeper.camera
        assert camera is not None
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
        self.transport = transport
        self.notifier = notifier or Notifier(env={})
        #: One per sensor the camera reads, in the board's order.
        self.channels = [SensorChannel(sensor.id, sensor.name, b, camera.fps, transport.packer(sensor.id))
                         for sensor, b in sensors]
        #: The sensors' pipelines on the board's spare cores (``workers``: how many threads; None: one per
        #: sensor beyond the first, as many as the cores beyond two).
        self.pool = SensorPool(spare_workers(len(self.channels)) if workers is None else workers)
        #: The services of the board's other cameras (this one is the lead when it has any).
        self.peers: list[Service] = []
        #: This service is one of a lead's peers: it takes commands from its inbox and leaves systemd alone.
        self.is_peer = False
        #: A gap without a good frame is said and ridden out, not an exit (``view`` at a terminal: nobody
        #: restarts it; under systemd ``run`` exits so that it is restarted).
        self.ride_out_stalls = False
        #: The live view (``run --view``): ``observe(frame, t_ns, pipeline, stats)`` after each frame, never blocking.
        self.view: LiveView | None = None
        #: The loop's CPU by stage, per frame (``run --stage-times``); None: not kept.
        self.stage_times: StageTimes | None = None
        #: The network publisher's frame-loop side (``[publish.NAME]``): ``offer_*`` copy and return, never blocking.
        self.network: NetworkOutput | None = None
        #: Protocol, streaming and rate divider, as the MCU's commands set them.
        self.link = LinkState(rate_divider=config.link.rate_divider, delivers=transport.delivers,
                              from_start=transport.from_start)
        self._inbox: deque[Command] = deque()
        #: Every sensor's STATUS (``status.calibration_unsaved``: the bundle could not be saved, bit5).
        self.status = StatusReporter(self.channels, self.stats, self.link, transport, config.status.period_s)
        self._max_gap_ns = int(gap_s * 1e9)
        self._last_good_ns = 0
        #: When the loop last went round (peers: what the lead's watchdog kick checks).
        self.heartbeat_ns = 0
        #: This loop processed a frame (the lead says READY once every loop did).
        self.ready = False
        #: The lead told systemd READY.
        self.notifier_ready = False

    @property
    def pipeline(self) -> Pipeline:
        """The first sensor's pipeline (the only one on a one-sensor camera)."""
        return self.channels[0].pipeline

    @property
    def camera(self) -> Camera | None:
        """The camera the loop reads (None while it is being reopened)."""
        return self.keeper.camera

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
        outcome = apply_command(command, self.link, self.channels, self.transport.protocols)
        if outcome is Outcome.REFUSED:
            self.stats.protocol_refused += 1
            if not self.is_peer:  # the lead says it once for the board
                log.warning("SET_PROTOCOL %d ignored: this link speaks %s", command.version,
                            ", ".join(f"v{v}" for v in self.transport.protocols))
        elif outcome is Outcome.SWITCHED and not self.is_peer:
            log.info("the MCU switched to protocol v%d", command.version)

    def post(self, command: Command) -> None:
        """From the lead's thread: a command for this service's loop (acted on before its next frame)."""
        self._inbox.append(command)

    def replace_pipeline(self, pipeline: Pipeline) -> None:
        """The first sensor uses ``pipeline`` from the next frame (a bundle re-oriented from the view; built off
        the frame thread)."""
        self.channels[0].replace_pipeline(pipeline)

    def close(self) -> None:
        """Close the camera the service opened itself and stop the sensor workers (idempotent)."""
        self.keeper.close()
        self.pool.close()

    # -- the loop ----------------------------------------------------------------------------

    def run(self, stop: threading.Event, duration_s: float | None = None,
            on_result: OnResult | None = None, max_frames: int | None = None) -> ServiceStats:
        """Process frames until ``stop`` is set, ``duration_s`` passes, ``max_frames`` camera frames were read
        (processed or refused: a dark camera or another sensor's frames end it too) or a finite source ends.

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
                return self._run(stop, duration_s, on_result, max_frames)
        finally:
            sys.setswitchinterval(switch_interval)

    def _run(self, stop: threading.Event, duration_s: float | None, on_result: OnResult | None,
             max_frames: int | None = None) -> ServiceStats:
        st = self.stats
        st.started_ns = self._last_good_ns = self.heartbeat_ns = self.clock.monotonic_ns()
        end_ns = None if duration_s is None else st.started_ns + int(duration_s * 1e9)
        self.status.next_ns = st.started_ns + self.status.period_ns
        try:
            while not stop.is_set():
                now_ns = self.heartbeat_ns = self.clock.monotonic_ns()
                if end_ns is not None and now_ns >= end_ns:
                    break
                if now_ns - self._last_good_ns > self._max_gap_ns:
                    gap = (f"no good camera frame for {(now_ns - self._last_good_ns) / 1e9:.1f} s "
                           f"(watchdog.max_frame_gap_s = {self._max_gap_ns / 1e9:g}; {st.camera_errors} camera faults)")
                    if not self.ride_out_stalls:
                        raise ServiceStalled(f"{gap}; exiting so systemd restarts")
                    st.stalls += 1
                    log.warning("%s; still waiting for the camera", gap)
                    self._last_good_ns = now_ns  # said once a gap
                try:
                    result = self._step(stop, now_ns)
                except _CameraEnded:
                    break
                self._after_step(result, on_result)
                if max_frames is not None and st.frames_read >= max_frames:
                    break
        finally:
            try:  # a last STATUS: the MCU sees the final counters
                self.status.send(self.clock.monotonic_ns(), self.camera is not None, self.network)
            except Exception as exc:  # noqa: BLE001 - shutting down anyway
                log.warning("final status not sent: %s", exc)
            if not self.is_peer:
                self.notifier.stopping()
            self.close()
        # debug: run's own summary says it (once: both reach journald under systemd)
        log.debug("camera %s stopped after %d frames (%d contacts, %d dropped and %d before the loop caught up, "
                 "%d camera faults, %d reopens, %d processing errors, %d light changes, %d baseline raises, "
                 "%d not processed: not of the bundle's sensor)",
                 self.camera_name, st.frames, st.contacts, st.frames_dropped, st.frames_dropped_before_loop,
                 st.camera_errors, st.reopens, st.processing_errors, st.light_changes, st.baseline_raises,
                 st.mismatched_frames)
        return st

    def _step(self, stop: threading.Event, now_ns: int) -> FrameResult | None:
        """One pass: reopen the camera or read a frame and process it; the first sensor's result, or None.

        Raises :class:`_CameraEnded` when a finite source has no more frames.
        """
        keeper = self.keeper
        if keeper.camera is None:  # reopening after a failure
            keeper.reopen_step(stop, now_ns)
            return None
        captured, dropped, read = keeper.read(stop, self.camera_config.timeout_s)
        if not read:
            for ch in self.channels:
                ch.fault_since_status = True
            return None
        if captured is None:
            raise _CameraEnded
        self.stats.frames_read += 1
        self.stats.frames_dropped += dropped
        result, device_fault = self._process(captured)
        if self.view is not None:  # the live view copies what it needs when an update is due; never waits
            self.view.observe(captured.frame, captured.t_ns, self.pipeline, self.stats)
        if not device_fault:  # a camera delivering wrong frames counts towards the frame gap
            self._last_good_ns = self.clock.monotonic_ns()
        return result

    def _after_step(self, result: FrameResult | None, on_result: OnResult | None) -> None:
        """READY once, the watchdog kick, the MCU's commands, the caller's hook, STATUS when due."""
        if result is not None and not self.ready:
            self.ready = True
            STARTUP.mark(f"first frame of camera {self.camera_name}")
        if not self.is_peer:
            self._tell_systemd()
            for command in self.transport.poll_commands():
                self.handle(command)
        while self._inbox:
            self.handle(self._inbox.popleft())
        if result is not None and on_result is not None:
            on_result(result, self.stats)
        now_ns = self.clock.monotonic_ns()
        if now_ns >= self.status.next_ns:
            self.status.send(now_ns, self.camera is not None, self.network)

    def _tell_systemd(self) -> None:
        """The lead: READY once every camera processed a frame; the watchdog kick while every loop goes round."""
        if self.ready and not self.notifier_ready and all(p.ready for p in self.peers):
            self.notifier_ready = True
            self.notifier.ready("processing frames")
            log.info("first frame processed; %s", "streaming to the MCU" if self.transport.delivers
                     else "no link to an MCU: nothing is sent")
        if self.config.watchdog.enabled:
            now_ns = self.clock.monotonic_ns()
            # from the loop itself: a stuck loop (or a peer's, stuck in its camera driver) stops kicking
            if all(now_ns - p.heartbeat_ns <= self._max_gap_ns for p in self.peers):
                self.notifier.watchdog(now_ns / 1e9)

    def _process(self, captured: CapturedFrame) -> tuple[FrameResult | None, bool]:
        """Check and process one captured frame for every sensor: (the first sensor's result, None when no
        sensor processed the frame; a device fault).

        Every sensor's pipeline checks the frame and processes it (side by side on :attr:`pool`'s workers;
        :meth:`Pipeline.process <optitac_edge.core.pipeline.Pipeline.process>`); a frame of the wrong shape or
        type (the sensors share the camera's frame: all or none refuse it) is counted once; then, sensor by
        sensor in the board's order, the skips (dark, saturated), the counts, the network and the messages
        to the MCU.
        """
        st = self.stats
        first: FrameResult | None = None
        device_fault = False
        send = self.link.due(st.frames + 1)
        times = self.stage_times
        t0 = 0 if times is None else times.clock()
        for ch in self.channels:
            ch.take(captured)
        results = self.pool.run([ch.run_pipeline for ch in self.channels])
        t1 = 0 if times is None else times.clock()
        if results[0] is Skip.BAD:  # not a frame of this camera, for every sensor: counted once
            counts.frame_skipped(self.stats, self.channels[0], Skip.BAD)
            return None, True
        for ch, result in zip(self.channels, results):
            if isinstance(result, Exception):  # a per-frame failure never ends the service
                counts.processing_failed(self.stats, ch, result)
                device_fault = True  # a loop failing on every frame counts towards the frame gap
                continue
            if isinstance(result, Skip):  # dark or saturated for this sensor
                counts.frame_skipped(self.stats, ch, result)
                continue
            assert isinstance(result, FrameResult)
            self._deliver(ch, result, captured, send)
            if first is None:
                first = result
        if first is not None:
            st.frames += 1
            st.sent += int(send)
            if times is not None:
                times.add(t1 - t0, times.clock() - t1)
        return first, device_fault

    def _deliver(self, ch: SensorChannel, result: FrameResult, captured: CapturedFrame, send: bool) -> None:
        """One sensor's frame out: its counts, the network, the outbox's messages sent."""
        self._count(ch, result)
        if self.network is not None:
            self.network.offer_frame(ch.sensor_id, result, ch.degraded, ch.pipeline.signal, captured.frame,
                                     ch.pipeline.surface)
        for packet in ch.outbox.update(result, self.link, send, self.clock.monotonic_ns()):
            self.transport.send(packet)

    def _count(self, ch: SensorChannel, result: FrameResult) -> None:
        """The sensor's counters and flags from its frame (and a log line on the first and every 100th event)."""
        st = self.stats
        contact = result.n_contacts > 0
        ch.frames += 1
        ch.contacts += contact
        st.contacts += contact
        st.saturated_sent += result.saturated
        if result.light_changed:
            counts.light_changed(st, ch)
        if result.baseline_raised:
            counts.baseline_raised(st, ch, result.raised_fibers)
