"""Bring-up: open the board's devices from a board config.

The frame loop (:mod:`optitac_edge.service.loop`) takes what these open: each
camera (:func:`open_board_camera`, also the factory it reopens the camera
with), a link to the MCU (:func:`open_board_transport`) and the LED ring
(:func:`open_led`); its bundles come from :mod:`optitac_edge.service.bundles`.
"""

from __future__ import annotations

import inspect
import logging
from dataclasses import fields
from typing import Any

from optitac_edge.config import BoardConfig, LedConfig
from optitac_edge.errors import ConfigError, TransportError
from optitac_edge.io.cameras import BACKENDS, open_camera
from optitac_edge.io.cameras.base import Camera
from optitac_edge.io.device import load_backend
from optitac_edge.io.led import I2CBus, LedRing, NoLed, pwm_period_us
from optitac_edge.io.publishers import Publisher, open_publisher
from optitac_edge.io.transports import TRANSPORTS
from optitac_edge.io.transports.base import Transport

log = logging.getLogger(__name__)


def open_led(config: LedConfig, bus: I2CBus | None = None) -> LedRing | NoLed:
    """The ring a board config's ``[led]`` section describes (``bus`` overrides ``i2c_bus``),
    or a :class:`~optitac_edge.io.led.NoLed` when ``config.enabled`` is false."""
    if not config.enabled:
        return NoLed()
    return LedRing(config.i2c_bus if bus is None else bus, config.address, config.channels,
                   config.brightness, pwm_frequency_hz=config.pwm_frequency_hz, invert=config.invert,
                   open_drain=config.open_drain)


def config_warnings(config: BoardConfig) -> list[str]:
    """Legal but suspicious combinations of a board config, one line each (logged at start)."""
    out = []
    led = config.led
    for name, cam in config.cameras.items():
        key = f"cameras.{name}" if config.named_cameras else "camera"
        if led.enabled and cam.exposure_us > 0:
            period = pwm_period_us(led.pwm_frequency_hz)
            rem = cam.exposure_us % period
            if cam.exposure_us < 10 * period and min(rem, period - rem) > 0.02 * period:
                out.append(f"{key}.exposure_us {cam.exposure_us} is neither >= 10 LED PWM periods "
                           f"nor a multiple of one ({period:.2f} us): frame brightness will flicker")
        if cam.exposure_us > 1e6 / cam.fps:
            out.append(f"{key}.exposure_us {cam.exposure_us} is longer than a frame at "
                       f"{cam.fps:g} fps: the camera will run slower")
    return out


def log_config_warnings(config: BoardConfig) -> None:
    """Log each of :func:`config_warnings` (once, at start)."""
    for line in config_warnings(config):
        log.warning("%s: %s", config.source, line)


def camera_kwargs(config: BoardConfig, camera: str | None = None) -> dict[str, Any]:
    """Constructor arguments of a camera's backend: its typed keys, then its ``options`` for what the
    backend takes beyond them. ``camera`` names one of ``config.cameras`` (default: the first sensor's).

    The simulated camera renders one fiber patch in each region the board gives a sensor it reads.

    Raises
    ------
    ConfigError
        If an option sets what a typed key sets (``camera.options.fps``: use
        ``camera.fps``, which is validated), or names no parameter of the backend.
    """
    name = config.sensor.camera if camera is None else camera
    cam = config.cameras[name]
    backend = load_backend(BACKENDS, cam.backend, "camera backend", ConfigError)
    typed: dict[str, Any] = backend.board_kwargs(cam, config.regions_of(name), config.calibration.rest_frames)
    _check_camera_options(config, name, typed)
    return {**typed, **dict(cam.options)}


def _check_camera_options(config: BoardConfig, name: str, typed: dict[str, Any]) -> None:
    cam = config.cameras[name]
    key = f"cameras.{name}" if config.named_cameras else "camera"
    if not cam.options:
        return
    shadowed = {f.name for f in fields(cam)} | set(typed)
    try:
        params = inspect.signature(load_backend(BACKENDS, cam.backend, "camera backend", ConfigError)).parameters
    except ImportError:  # the backend's module cannot be imported here: it says why when opened
        return
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    for option in cam.options:
        where = config.origins.get(f"{key}.options.{option}", config.source)
        if option in shadowed:
            raise ConfigError(f"{where}: {key}.options.{option}: set it with the camera key that does "
                              f"({key}.{option if option in {f.name for f in fields(cam)} else '...'}), "
                              "which is checked")
        if not takes_any and (option not in params or option in ("clock", "regions")):
            known = sorted(set(params) - shadowed - {"self", "clock", "regions"})
            raise ConfigError(f"{where}: {key}.options.{option}: not an option of the {cam.backend} camera "
                              f"(its options: {', '.join(known) or 'none'})")


def open_board_camera(config: BoardConfig, camera: str | None = None) -> Camera:
    """Open a camera of the board (default: the first sensor's)."""
    name = config.sensor.camera if camera is None else camera
    return open_camera(config.cameras[name].backend, **camera_kwargs(config, name))


def open_board_transport(config: BoardConfig) -> Transport:
    """The link to the MCU ``[link] transport`` names, opened by its class from the ``[link]`` keys."""
    cls = load_backend(TRANSPORTS, config.link.transport, "transport", TransportError)
    transport: Transport = cls.from_link(config.link, [s.sensor.id for s in config.sensors])
    return transport


def open_board_publisher(config: BoardConfig) -> Publisher | None:
    """Where the board's contacts go besides the MCU: every ``[publish.NAME]`` (Zenoh, Foxglove, an MCAP
    recording, ...), each opened by its registry name with its section's arguments and the ``[network]``
    namespace; one publisher for all; None when none is on."""
    namespace = config.network.namespace
    opened: list[Publisher] = []
    try:
        for name, section in config.publish.items():
            opened.append(open_publisher(name, namespace=namespace, **section.kwargs()))
    except BaseException:
        for publisher in opened:
            publisher.close()
        raise
    if len(opened) > 1:
        from optitac_edge.io.publishers.fanout import FanoutPublisher

        return FanoutPublisher(opened)
    return opened[0] if opened else None
