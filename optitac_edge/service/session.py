"""One board's service, start to end: open its devices, get the bundle, run the loop, close everything.

``optitac-edge run`` is this plus a status line::

    with BoardSession(config, cal_path) as session:
        bundle = session.bundle()          # loaded, or calibrated from the first rest frames
        stats = session.run(stop, duration_s=10.0)
"""

from __future__ import annotations

from contextlib import ExitStack, closing
from pathlib import Path
from threading import Event
from types import TracebackType
from typing import TYPE_CHECKING, Any

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.io.cameras.base import Camera
from optitac_edge.io.clock import SYSTEM_CLOCK, Clock
from optitac_edge.io.led import LedRing, NoLed
from optitac_edge.io.sdnotify import Notifier
from optitac_edge.io.transports.base import Transport
from optitac_edge.service.board_config import BoardConfig
from optitac_edge.service.loop import OnResult, Service, ServiceStats
from optitac_edge.service.wiring import (
    log_config_warnings,
    obtain_bundle,
    open_board_camera,
    open_board_transport,
    open_led,
)

if TYPE_CHECKING:
    from typing_extensions import Self


class BoardSession:
    """The LED ring, camera and link of one board config, open for one run of the service.

    Parameters
    ----------
    config : BoardConfig
    cal_path : path, optional
        A bundle to use instead of the board's ``calibration.bundle`` (must exist).
    notifier : Notifier, optional
        systemd notifications (default: from the environment; closed with the session).
    clock : Clock
        The loop's clock.
    """

    def __init__(self, config: BoardConfig, cal_path: Path | None = None, notifier: Notifier | None = None,
                 clock: Clock = SYSTEM_CLOCK) -> None:
        self.config = config
        self.cal_path = cal_path
        self.clock = clock
        self._notifier = notifier
        self._stack = ExitStack()
        self._bundle: CalibrationBundle | None = None
        #: Why the bundle calibrated at start could not be saved (None: saved or loaded).
        self.unsaved: str | None = None
        #: The service of the last :meth:`run`.
        self.service: Service | None = None
        self.led: LedRing | NoLed | None = None
        self.camera: Camera | None = None
        self.transport: Transport | None = None
        #: The live view, when :meth:`open_view` was called.
        self.view: Any = None

    def __enter__(self) -> Self:
        log_config_warnings(self.config)
        try:
            self.notifier = self._stack.enter_context(closing(self._notifier or Notifier()))
            led = open_led(self.config.led)
            self._stack.callback(led.close)
            led.set_brightness(self.config.led.brightness)
            self.led = led
            self.camera = self._stack.enter_context(open_board_camera(self.config))
            self.transport = self._stack.enter_context(open_board_transport(self.config))
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Close the link, the camera and the LED ring (idempotent)."""
        self._stack.close()

    @property
    def calibrates(self) -> bool:
        """:meth:`bundle` will calibrate the fiber map from the camera (no bundle to load)."""
        path = self.cal_path if self.cal_path is not None else self.config.calibration.bundle_path
        return path is None or (self.cal_path is None and not Path(path).exists())

    def bundle(self) -> CalibrationBundle:
        """The calibration bundle (loaded, or calibrated from the camera's rest frames; once)."""
        if self._bundle is None:
            assert self.camera is not None, "open the session first (with BoardSession(...) as session)"
            self._bundle, self.unsaved = obtain_bundle(self.config, self.camera, self.cal_path, self.led)
        return self._bundle

    def open_view(self, bind: str) -> str:
        """Serve the live view on ``bind`` (``HOST:PORT``) while the session runs; returns its URL.

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

    def run(self, stop: Event, duration_s: float | None = None, on_result: OnResult | None = None) -> ServiceStats:
        """Run the frame loop until ``stop``, ``duration_s`` or the camera's end (see :meth:`Service.run`)."""
        assert self.transport is not None, "open the session first (with BoardSession(...) as session)"
        config = self.config
        self.service = service = Service(config, self.bundle(), self.camera, self.transport, self.notifier,
                                         camera_factory=lambda: open_board_camera(config), clock=self.clock)
        service.calibration_unsaved = self.unsaved is not None
        if self.view is not None:
            service.view = self.view
            self.view.swap_pipeline = service.replace_pipeline
        return service.run(stop, duration_s=duration_s, on_result=on_result)


def _link_state(transport: Transport) -> str:
    """A few words on the link to the MCU, for the view."""
    if not transport.delivers:
        return "none"
    connected = getattr(transport, "connected", None)
    state = "" if connected is None else (" connected" if connected else " disconnected")
    return f"{type(transport).__name__.removesuffix('Transport').lower()}{state}, sent {transport.counters.sent}"
