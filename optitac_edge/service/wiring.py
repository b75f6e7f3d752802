"""Bring-up: open the board's devices and get a calibration bundle, from a board config.

The frame loop (:mod:`optitac_edge.service.loop`) takes what these open: a
camera (:func:`open_board_camera`, also the factory it reopens the camera
with), a link to the MCU (:func:`open_board_transport`), the LED ring
(:func:`open_led`) and a bundle (:func:`load_or_calibrate`: loaded, or
calibrated from the camera's rest frames; only then is the offline
calibration code, and with it scipy, imported).
"""

from __future__ import annotations

import inspect
import logging
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.errors import BundleError, CameraError, ConfigError, OptiTacError, OutputError
from optitac_edge.io.bundle_file import load_bundle, save_bundle
from optitac_edge.io.cameras import BACKENDS, open_camera
from optitac_edge.io.cameras.base import Camera
from optitac_edge.io.device import load_backend
from optitac_edge.io.layout_csv import load_layout_csv
from optitac_edge.io.led import I2CBus, LedRing, NoLed, pwm_period_us
from optitac_edge.io.transports import open_transport
from optitac_edge.io.transports.base import Transport
from optitac_edge.service.board_config import BoardConfig, LedConfig

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
    cam, led = config.camera, config.led
    if led.enabled and cam.exposure_us > 0:
        period = pwm_period_us(led.pwm_frequency_hz)
        rem = cam.exposure_us % period
        if cam.exposure_us < 10 * period and min(rem, period - rem) > 0.02 * period:
            out.append(f"camera.exposure_us {cam.exposure_us} is neither >= 10 LED PWM periods "
                       f"nor a multiple of one ({period:.2f} us): frame brightness will flicker")
    if cam.exposure_us > 1e6 / cam.fps:
        out.append(f"camera.exposure_us {cam.exposure_us} is longer than a frame at "
                   f"{cam.fps:g} fps: the camera will run slower")
    return out


def log_config_warnings(config: BoardConfig) -> None:
    """Log each of :func:`config_warnings` (once, at start)."""
    for line in config_warnings(config):
        log.warning("%s: %s", config.source, line)


def camera_kwargs(config: BoardConfig) -> dict[str, Any]:
    """Constructor arguments of the configured camera backend: the typed ``[camera]`` keys, then
    ``camera.options`` for what the backend takes beyond them.

    Raises
    ------
    ConfigError
        If an option sets what a typed key sets (``camera.options.fps``: use
        ``camera.fps``, which is validated), or names no parameter of the backend.
    """
    cam = config.camera
    typed: dict[str, Any]
    if cam.backend == "sim":
        typed = {"fps": cam.fps, "width": cam.width, "height": cam.height, "rgb": cam.pixel_format == "rgb",
                 "rest_frames": max(config.calibration.rest_frames, 10), "queue_frames": cam.queue_frames}
    elif cam.backend == "recording":
        typed = {"path": cam.recording, "realtime": True}
    elif cam.backend == "picamera2":
        typed = {"width": cam.width, "height": cam.height, "fps": cam.fps, "camera_num": cam.index,
                 "pixel_format": cam.pixel_format, "exposure_us": cam.exposure_us or None,
                 "analogue_gain": cam.gain or None, "warmup_frames": cam.warmup_frames,
                 "timeout_s": cam.timeout_s, "queue_frames": cam.queue_frames}
    elif cam.backend == "v4l2":  # exposure in driver units goes in camera.options.exposure
        source = {"pipeline": cam.pipeline} if cam.pipeline else {"device": cam.device}
        typed = {**source, "width": cam.width, "height": cam.height, "fps": cam.fps,
                 "gain": cam.gain or None, "queue_frames": cam.queue_frames}
    else:
        typed = {}
    _check_camera_options(config, typed)
    return {**typed, **dict(cam.options)}


def _check_camera_options(config: BoardConfig, typed: dict[str, Any]) -> None:
    cam = config.camera
    if not cam.options:
        return
    shadowed = {f.name for f in fields(cam)} | set(typed)
    try:
        params = inspect.signature(load_backend(BACKENDS, cam.backend, "camera backend", ConfigError)).parameters
    except ImportError:  # the backend's module cannot be imported here: it says why when opened
        return
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    for name in cam.options:
        where = config.origins.get(f"camera.options.{name}", config.source)
        if name in shadowed:
            raise ConfigError(f"{where}: camera.options.{name}: set it with the camera key that does "
                              f"(camera.{name if name in {f.name for f in fields(cam)} else '...'}), "
                              "which is checked")
        if not takes_any and (name not in params or name == "clock"):
            known = sorted(set(params) - shadowed - {"self", "clock"})
            raise ConfigError(f"{where}: camera.options.{name}: not an option of the {cam.backend} camera "
                              f"(its options: {', '.join(known) or 'none'})")


def open_board_camera(config: BoardConfig) -> Camera:
    return open_camera(config.camera.backend, **camera_kwargs(config))


def open_board_transport(config: BoardConfig) -> Transport:
    link = config.link
    if link.transport == "serial":
        # a port that is not there yet (MCU unplugged, udev not done) is waited for, not fatal:
        # the service streams as soon as it appears
        return open_transport("serial", url=link.serial_url, baudrate=link.baudrate, sensor_id=config.sensor.id,
                              require_port=False)
    if link.transport == "can":
        return open_transport("can", channel=link.can_channel, interface=link.can_interface,
                              sensor_id=config.sensor.id, protocol=link.can_protocol,
                              bitrate=link.can_bitrate if link.can_interface == "socketcan" else None)
    return open_transport("null")


def adjust_led(config: BoardConfig, camera: Camera, led: LedRing | NoLed) -> float:
    """Lower the LED ring until the brightest fibers stay below saturation; returns the brightness.

    Each trial sets the brightness, lets two frames expose, and takes the
    ``led.peak_percentile`` of the third frame's gray levels.
    """
    from optitac_edge.calibration.led_brightness import adjust_brightness_for_saturation, fiber_peak
    from optitac_edge.core.frames import to_gray

    def read_peak(brightness: float) -> float:
        led.set_brightness(brightness)
        for _ in range(2):
            camera.read(config.camera.timeout_s)
        captured = camera.read(config.camera.timeout_s)
        if captured is None:
            raise CameraError("camera ended while adjusting the LED brightness")
        return fiber_peak(to_gray(captured.frame, camera.pixel_format), None, config.led.peak_percentile)

    result = adjust_brightness_for_saturation(read_peak, max_peak=config.led.max_peak,
                                              start=config.led.brightness)
    log.info("LED brightness %.3f (peak %.0f after %d trials%s)", result.brightness, result.peak,
             result.measurements, "" if result.ok else ", still saturated at the lowest setting")
    return result.brightness


def load_or_calibrate(config: BoardConfig, camera: Camera, cal_path: Path | None,
                      led: LedRing | NoLed | None = None) -> CalibrationBundle:
    """The calibration bundle: loaded if it exists, else calibrated from the camera's rest frames.

    ``cal_path`` (the command line's ``--cal``) must exist; the board's
    ``calibration.bundle`` is calibrated and saved when missing, unless
    ``calibration.if_missing = "fail"``. Only calibrating imports the offline code.
    A bundle that cannot be saved is still returned (see :func:`obtain_bundle`).
    """
    return obtain_bundle(config, camera, cal_path, led)[0]


def obtain_bundle(config: BoardConfig, camera: Camera, cal_path: Path | None,
                  led: LedRing | NoLed | None = None) -> tuple[CalibrationBundle, str | None]:
    """:func:`load_or_calibrate`, and why a freshly calibrated bundle could not be saved (or None).

    A full or read-only state directory does not take the service down: the
    bundle works from memory (it is calibrated again at the next start); the
    failure is logged once and returned for STATUS.
    """
    path = cal_path if cal_path is not None else config.calibration.bundle_path
    if path is not None and Path(path).exists():
        return load_bundle(path), None
    if path is not None and cal_path is not None:
        raise BundleError(f"{path}: calibration bundle not found")
    if config.calibration.if_missing == "fail":
        raise OptiTacError(f"no calibration bundle at {path} and calibration.if_missing = 'fail'")
    bundle = calibrate_from_camera(config, camera, led)
    if path is None:
        return bundle, None
    try:
        bundle = save_bundle(bundle, path)
    except OutputError as exc:
        log.error("calibration bundle not saved (%s); running on it from memory, it will be calibrated "
                  "again at the next start", exc)
        return bundle, str(exc)
    log.info("saved the calibration bundle to %s", path)
    return bundle, None


def calibrate_from_camera(config: BoardConfig, camera: Camera,
                          led: LedRing | NoLed | None = None) -> CalibrationBundle:
    """The fiber map from ``calibration.rest_frames`` frames of ``camera`` (nothing may touch the skin).

    With an LED ring (``led``) and ``led.adjust_at_calibration``, its brightness
    is first lowered until no fiber saturates.
    """
    from optitac_edge.calibration.fibers import calibrate_fibers

    if led is not None and config.led.enabled and config.led.adjust_at_calibration:
        adjust_led(config, camera, led)
    n = config.calibration.rest_frames
    log.info("calibrating the fiber map from %d rest frames", n)
    frames: list[np.ndarray] = []
    while len(frames) < n:
        captured = camera.read(config.camera.timeout_s)
        if captured is None:
            raise CameraError("camera ended before the rest frames were captured")
        frames.append(captured.frame.copy())
    layout_path = config.calibration.layout_path
    layout = load_layout_csv(layout_path) if layout_path is not None else None
    return calibrate_fibers(frames, camera.pixel_format, layout=layout,
                            rotation_hint_deg=config.calibration.rotation_deg, mirror=config.calibration.mirror)
