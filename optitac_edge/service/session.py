"""One board's service, start to end: open its devices, get the bundles, run the loops, close everything.

``optitac-edge run`` is this plus a status line::

    with BoardSession(config, cal_path) as session:
        bundle = session.bundle()          # loaded, or calibrated from the first rest frames
        stats = session.run(stop, duration_s=10.0)
"""

from __future__ import annotations

import functools
import logging
import threading
from contextlib import ExitStack, closing
from pathlib import Path
from threading import Event
from types import TracebackType
from typing import TYPE_CHECKING

from optitac_edge.config import BoardConfig, SensorConfig
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.compiled import kernel_status
from optitac_edge.io.cameras.base import Camera
from optitac_edge.io.clock import SYSTEM_CLOCK, Clock
from optitac_edge.io.led import LedRing, NoLed
from optitac_edge.io.publishers import Publisher
from optitac_edge.io.sdnotify import Notifier
from optitac_edge.io.startup import STARTUP
from optitac_edge.io.transports.base import Transport
from optitac_edge.service.bundles import SensorBundle, obtain_bundles
from optitac_edge.service.loop import OnResult, Service, ServiceStats
from optitac_edge.service.network import NetworkOutput, NetworkSensor
from optitac_edge.service.stage_times import StageTimes
from optitac_edge.service.wiring import (
    log_config_warnings,
    open_board_camera,
    open_board_publisher,
    open_board_transport,
    open_led,
)

if TYPE_CHECKING:
    from typing_extensions import Self

    from optitac_edge.service.view.live import LiveView

log = logging.getLogger(__name__)

#: Pictures (image, surface, overlay) per second and sensor for Foxglove when [network] picture_hz is 0.
DEFAULT_PICTURE_HZ = 10.0


class BoardSession:
    """The LED ring, cameras and link of one board config, open for one run of the service.

    A board with several cameras runs one frame loop per camera: the first
    sensor's camera in the calling thread (the lead), every other in a thread
    of its own (see :class:`~optitac_edge.service.loop.Service`).

    Parameters
    ----------
    config : BoardConfig
    cal_path : path, optional
        A bundle to use instead of the board's ``calibration.bundle`` (must exist; one sensor only).
    notifier : Notifier, optional
        systemd notifications (default: from the environment; closed with the session).
    clock : Clock
        The loops' clock.
    """

    def __init__(self, config: BoardConfig, cal_path: Path | None = None, notifier: Notifier | None = None,
                 clock: Clock = SYSTEM_CLOCK) -> None:
        self.config = config
        self.cal_path = cal_path
        self.clock = clock
        self._notifier = notifier
        self._stack = ExitStack()
        self._bundles: dict[str, list[SensorBundle]] | None = None
        #: The services of the last :meth:`run`, the lead's first.
        self.services: list[Service] = []
        self.led: LedRing | NoLed | None = None
        #: The open cameras by name, the lead's first.
        self.cameras: dict[str, Camera] = {}
        self.transport: Transport | None = None
        #: The live view, when :meth:`open_view` was called.
        self.view: LiveView | None = None
        #: Gaps without a camera frame are said and ridden out (``view``), not an exit (``run``).
        self.ride_out_stalls = False
        #: Keep each loop's CPU by stage (``run --stage-times``; :attr:`Service.stage_times`).
        self.stage_times = False
        #: The board's network publisher (``[publish.NAME]``; None when off), and its publishing thread once running.
        self.publisher: Publisher | None = None
        self.network: NetworkOutput | None = None

    @property
    def camera(self) -> Camera | None:
        """The lead camera (the first sensor's)."""
        return self.cameras.get(self.config.sensor.camera)

    @property
    def service(self) -> Service | None:
        """The lead service of the last :meth:`run`."""
        return self.services[0] if self.services else None

    @property
    def unsaved(self) -> str | None:
        """Why a bundle calibrated at start could not be saved (None: all saved or loaded)."""
        found = [b.unsaved for group in (self._bundles or {}).values() for b in group if b.unsaved]
        return found[0] if found else None

    def _camera_names(self) -> list[str]:
        lead = self.config.sensor.camera
        return [lead, *(name for name in self.config.cameras if name != lead)]

    def __enter__(self) -> Self:
        log_config_warnings(self.config)
        log.info("%s", kernel_status()[1])
        try:
            self.notifier = self._stack.enter_context(closing(self._notifier or Notifier()))
            led = open_led(self.config)
            self._stack.callback(led.close)
            led.set_brightness(self.config.led.brightness)
            self.led = led
            for name in self._camera_names():
                self.cameras[name] = self._stack.enter_context(open_board_camera(self.config, name))
            STARTUP.mark("cameras opened")
            self.transport = self._stack.enter_context(open_board_transport(self.config))
            STARTUP.mark("link opened")
            self.publisher = open_board_publisher(self.config)
            if self.publisher is not None:
                self._stack.callback(self.publisher.close)
                log.info("publishing on %s", self.publisher.where)
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Close the link, the cameras and the LED ring (idempotent)."""
        self._stack.close()

    @property
    def calibrates(self) -> bool:
        """:meth:`bundles` will calibrate some sensor's fiber map from its camera (no bundle to load)."""
        if self.cal_path is not None:
            return False
        return any(s.calibration.bundle_path is None or not s.calibration.bundle_path.exists()
                   for s in self.config.sensors)

    def bundles(self) -> dict[str, list[SensorBundle]]:
        """Every sensor's bundle by camera (loaded, or calibrated from the camera's rest frames; once)."""
        if self._bundles is None:
            assert self.cameras, "open the session first (with BoardSession(...) as session)"
            self._bundles = {name: obtain_bundles(self.config, name, cam, self.cal_path,
                                                  self.led if k == 0 else None)
                             for k, (name, cam) in enumerate(self.cameras.items())}
        return self._bundles

    def bundle(self) -> CalibrationBundle:
        """The first sensor's bundle."""
        return self.bundles()[self.config.sensor.camera][0].bundle

    def open_view(self, bind: str) -> str:
        """Serve the live view of the first sensor on ``bind`` (``HOST:PORT``) while the session runs; returns
        its URL.

        Everything the view does runs in its own threads: the frame loop only
        hands over a copy when an update is due and never waits for a viewer.
        """
        from optitac_edge.service.view.live import LiveView
        from optitac_edge.service.view.server import ViewServer

        assert self.camera is not None and self.transport is not None, "open the session first"
        transport = self.transport
        view = LiveView(self.bundle(), self.camera.pixel_format, link=lambda: _link_state(transport))
        view.bundle_path = self.cal_path or self.config.calibration.bundle_path
        self._stack.callback(view.close)
        server = self._stack.enter_context(ViewServer(view, bind))
        self.view = view
        return server.url

    def open_network(self) -> NetworkOutput | None:
        """The publishing thread for every sensor of the board (once; None when publishing is off)."""
        if self.publisher is None or self.network is not None:
            return self.network
        net = self.config.network
        sensors = [network_sensor(found.sensor.sensor, found.bundle)
                   for group in self.bundles().values() for found in group]
        foxglove = "foxglove" in self.config.publish
        self.network = NetworkOutput(self.publisher, sensors, queue=net.queue, signal_hz=net.signal_hz,
                                     picture_hz=net.picture_hz or (DEFAULT_PICTURE_HZ if foxglove else 0.0))
        self._stack.callback(self.network.close)
        return self.network

    def run(self, stop: Event, duration_s: float | None = None, on_result: OnResult | None = None,
            max_frames: int | None = None) -> ServiceStats:
        """Run the frame loops until ``stop``, ``duration_s``, the lead camera's ``max_frames`` or its end (see
        :meth:`Service.run`); the lead's counters.

        With several cameras, ``on_result`` is called from each camera's loop; when
        the lead's loop ends it sets ``stop`` so the others end too, and a loop that
        failed (e.g. :class:`~optitac_edge.service.loop.ServiceStalled`) sets ``stop``
        and its exception is raised here.
        """
        assert self.transport is not None, "open the session first (with BoardSession(...) as session)"
        config = self.config
        bundles = self.bundles()
        self.services = []
        for name, camera in self.cameras.items():
            group = bundles[name]
            service = Service(config, None, camera, self.transport, self.notifier,
                              camera_factory=functools.partial(open_board_camera, config, name), clock=self.clock,
                              sensors=[(b.sensor.sensor, b.bundle) for b in group],
                              camera_config=config.cameras[name], camera_name=name)
            service.status.calibration_unsaved = any(b.unsaved is not None for b in group)
            service.ride_out_stalls = self.ride_out_stalls
            if self.stage_times:
                service.stage_times = StageTimes()
            self.services.append(service)
        STARTUP.mark("pipelines and kernel plans")
        lead, peers = self.services[0], self.services[1:]
        lead.peers = peers
        for peer in peers:
            peer.is_peer = True
        if self.view is not None:
            lead.view = self.view
            self.view.swap_pipeline = lead.replace_pipeline
        network = self.open_network()
        for service in self.services:
            service.network = network
        failures: list[BaseException] = []
        threads = [threading.Thread(target=_run_peer, args=(peer, stop, duration_s, on_result, failures),
                                    name=f"optitac-camera-{name}", daemon=True)
                   for peer, name in zip(peers, list(self.cameras)[1:])]
        for thread in threads:
            thread.start()
        try:
            stats = lead.run(stop, duration_s=duration_s, on_result=on_result, max_frames=max_frames)
        finally:
            if threads:
                stop.set()
                for thread in threads:
                    thread.join()
        if failures:
            raise failures[0]
        return stats


def network_sensor(sensor: SensorConfig, bundle: CalibrationBundle) -> NetworkSensor:
    """A sensor as the network sees it: its id, name, fiber centres, dead fibers and calibration."""
    xy = bundle.layout.xy_mm
    region = tuple(sensor.region)
    px = bundle.fibers.centroid_px - (region[:2] if region else (0, 0))
    return NetworkSensor(sensor.id, sensor.name, xy[:, 0].astype("float32"), xy[:, 1].astype("float32"),
                         bundle.fibers.dead.copy(), bundle.calibration_id, fiber_px=px, region=region,
                         image_rows=bundle.fibers.height)


def _run_peer(service: Service, stop: Event, duration_s: float | None, on_result: OnResult | None,
              failures: list[BaseException]) -> None:
    """A peer camera's loop in its own thread; a failure stops the board and is raised by the lead's thread."""
    try:
        service.run(stop, duration_s=duration_s, on_result=on_result)
    except BaseException as exc:  # noqa: BLE001 - handed to the session's thread, which raises it
        failures.append(exc)
        stop.set()


def _link_state(transport: Transport) -> str:
    """A few words on the link to the MCU, for the view."""
    if not transport.delivers:
        return "none"
    connected = getattr(transport, "connected", None)
    state = "" if connected is None else (" connected" if connected else " disconnected")
    return f"{type(transport).__name__.removesuffix('Transport').lower()}{state}, sent {transport.counters.sent}"
