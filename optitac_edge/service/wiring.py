"""Bring-up: open the board's devices from a board config, each through its kind's registry.

One recipe for every kind: the registry (``module:Class`` by name) gives the class, and
``Class.from_config(section, board)`` opens it from its own section and what it sees of the board
(:meth:`~optitac_edge.config.BoardConfig.view`). The frame loop (:mod:`optitac_edge.service.loop`) takes
what these open: each camera (:func:`open_board_camera`, also the factory it reopens the camera with), a
link to the MCU (:func:`open_board_transport`), the publishers (:func:`open_board_publisher`) and the LED
ring (:func:`open_led`); its bundles come from :mod:`optitac_edge.service.bundles`.
"""

from __future__ import annotations

import logging

from optitac_edge.config import BoardConfig
from optitac_edge.io.cameras import CAMERAS
from optitac_edge.io.cameras.base import Camera
from optitac_edge.io.led import LEDS, LedRing, NoLed, pwm_period_us
from optitac_edge.io.publishers import PUBLISHERS, Publisher
from optitac_edge.io.transports import TRANSPORTS
from optitac_edge.io.transports.base import Transport

log = logging.getLogger(__name__)


def open_led(config: BoardConfig) -> LedRing | NoLed:
    """The ring the board's ``[led]`` section describes (its ``driver`` from :data:`~optitac_edge.io.led.LEDS`),
    or a :class:`~optitac_edge.io.led.NoLed` when ``led.enabled`` is false."""
    if not config.led.enabled:
        return NoLed()
    return LEDS.open(config.led.driver, config.led, config.view("led"))


def config_warnings(config: BoardConfig) -> list[str]:
    """Legal but suspicious combinations of a board config, one line each (logged at start)."""
    out = []
    led = config.led
    for name, cam in config.cameras.items():
        key = config.camera_key(name)
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


def open_board_camera(config: BoardConfig, camera: str | None = None) -> Camera:
    """Open a camera of the board (default: the first sensor's) from its section."""
    name = config.sensor.camera if camera is None else camera
    section = config.cameras[name]
    return CAMERAS.open(section.backend, section, config.view(config.camera_key(name)))


def open_board_transport(config: BoardConfig) -> Transport:
    """The link to the MCU ``[link] transport`` names, opened from the ``[link]`` keys."""
    return TRANSPORTS.open(config.link.transport, config.link, config.view("link"))


def open_board_publisher(config: BoardConfig) -> Publisher | None:
    """Where the board's contacts go besides the MCU: every ``[publish.NAME]`` (Zenoh, Foxglove, an MCAP
    recording, ...), each opened by its registry name from its section; one publisher for all; None when none
    is on."""
    opened: list[Publisher] = []
    try:
        for name, section in config.publish.items():
            opened.append(PUBLISHERS.open(name, section, config.view(f"publish.{name}")))
    except BaseException:
        for publisher in opened:
            publisher.close()
        raise
    if len(opened) > 1:
        from optitac_edge.io.publishers.fanout import FanoutPublisher

        return FanoutPublisher(opened)
    return opened[0] if opened else None
