"""Each sensor's calibration bundle at start: loaded and checked, or calibrated from its camera's rest frames.

A bundle is loaded when its file exists and checked against the board: a
sensor that the board places in a region of its camera's frame needs a bundle
placed in that same region (``calibrate fibers --sensor ID``), and a sensor
that fills its frame a bundle that does too. Without a bundle, the sensors of
one camera are calibrated from the same rest frames (each on its region's
crop, then placed in the frame); only then is the offline calibration code,
and with it scipy, imported.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from optitac_edge.config import BoardConfig, BoardSensor
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.fiber_table import FiberTable
from optitac_edge.core.fingerprint import SensorMismatchError, check_sensor
from optitac_edge.errors import BundleError, CameraError, ConfigError, OptiTacError, OutputError
from optitac_edge.io.bundle_file import load_bundle, save_bundle
from optitac_edge.io.cameras.base import Camera
from optitac_edge.io.layout_csv import load_layout_csv
from optitac_edge.io.led import LedRing, NoLed

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SensorBundle:
    """A sensor of the board with its bundle, and why a bundle calibrated at start was not saved (or None)."""

    sensor: BoardSensor
    bundle: CalibrationBundle
    unsaved: str | None = None


def obtain_bundles(config: BoardConfig, camera_name: str, camera: Camera, cal_path: Path | None = None,
                   led: LedRing | NoLed | None = None) -> list[SensorBundle]:
    """The bundle of every sensor ``camera`` reads (``config.sensors_of(camera_name)``), in the board's order.

    ``cal_path`` (the command line's ``--cal``) must exist and serves a board
    with one sensor only. A sensor's missing ``calibration.bundle`` is
    calibrated from the camera's rest frames and saved, unless
    ``calibration.if_missing = "fail"``. A bundle that cannot be saved is still
    used (see :class:`SensorBundle`): a full or read-only state directory does
    not take the service down; the failure is logged once and goes into STATUS.
    """
    sensors = config.sensors_of(camera_name)
    if cal_path is not None and len(config.sensors) > 1:
        raise ConfigError(f"--cal {cal_path}: the board has {len(config.sensors)} sensors; "
                          "give --sensor ID with --cal, or set each sensor's bundle in the board config")
    rest: list[np.ndarray] | None = None
    out = []
    for sensor in sensors:
        path = cal_path if cal_path is not None else sensor.calibration.bundle_path
        if path is not None and Path(path).exists():
            bundle = sensor.check_bundle(load_bundle(path), path)
            if cal_path is not None or sensor.calibration.if_mismatched != "remap":
                out.append(SensorBundle(sensor, bundle))  # the pipeline checks it at its first baseline
                continue
            if rest is None:
                rest = read_rest_frames(config, camera, led, "checking the bundles against")
            try:
                check_sensor(bundle, rest, camera.pixel_format, f"{sensor.label}: the camera's rest frames")
                out.append(SensorBundle(sensor, bundle))
                continue
            except SensorMismatchError as exc:
                log.warning("%s; mapping the fibers again from the rest frames (calibration.if_mismatched = "
                            "'remap')", exc)
            remapped = _calibrate(sensor, rest, camera.pixel_format)  # before the old one is moved
            log.warning("%s: the old bundle is kept as %s", sensor.label, _set_aside(Path(path)))
            out.append(SensorBundle(sensor, *_save(remapped, path, sensor)))
            continue
        if path is not None and cal_path is not None:
            raise BundleError(f"{path}: calibration bundle not found")
        if sensor.calibration.if_missing == "fail":
            who = f"{sensor.label}: " if config.listed_sensors else ""
            raise OptiTacError(f"{who}no calibration bundle at {path} and calibration.if_missing = 'fail'")
        if rest is None:
            rest = read_rest_frames(config, camera, led)
        bundle = _calibrate(sensor, rest, camera.pixel_format)
        out.append(SensorBundle(sensor, *_save(bundle, path, sensor)))
    return out


def _set_aside(path: Path) -> Path:
    """Rename a bundle the camera no longer fits to ``NAME.another-sensor[-K].npz`` beside it (never deleted:
    it may be the other skin's), and return the new name."""
    for k in range(1000):
        kept = path.with_name(f"{path.stem}.another-sensor{'' if k == 0 else f'-{k}'}{path.suffix}")
        if not kept.exists() and not kept.is_symlink():
            try:
                os.rename(path, kept)
            except OSError as exc:
                raise OutputError(f"{path}: cannot set the mismatched bundle aside as {kept.name}: "
                                  f"{exc.strerror or exc}") from None
            return kept
    raise OutputError(f"{path}: 1000 bundles of other sensors beside it already; move some away")


def _save(bundle: CalibrationBundle, path: Path | None, sensor: BoardSensor) -> tuple[CalibrationBundle, str | None]:
    if path is None:
        return bundle, None
    try:
        bundle = save_bundle(bundle, path)
    except OutputError as exc:
        log.error("%s: calibration bundle not saved (%s); running on it from memory, it will be calibrated "
                  "again at the next start", sensor.label, exc)
        return bundle, str(exc)
    log.info("%s: saved the calibration bundle to %s", sensor.label, path)
    return bundle, None


def obtain_bundle(config: BoardConfig, camera: Camera, cal_path: Path | None,
                  led: LedRing | NoLed | None = None) -> tuple[CalibrationBundle, str | None]:
    """The bundle of a board's only sensor (or the one ``config`` was narrowed to), and why it was not saved.

    Raises
    ------
    ConfigError
        The board has several sensors and ``config`` was not narrowed to one.
    """
    one = config.for_sensor(config.selected)
    found = obtain_bundles(one, one.sensor.camera, camera, cal_path, led)[0]
    return found.bundle, found.unsaved


def read_rest_frames(config: BoardConfig, camera: Camera, led: LedRing | NoLed | None = None,
                     doing: str = "calibrating the fiber map from") -> list[np.ndarray]:
    """``calibration.rest_frames`` frames of ``camera`` (nothing may touch the skins), copied; ``doing``: what
    they are for, for the log line.

    With an LED ring (``led``) and ``led.adjust_at_calibration``, its
    brightness is first lowered until no fiber saturates.
    """
    if led is not None and config.led.enabled and config.led.adjust_at_calibration:
        adjust_led(config, camera, led)
    n = config.calibration.rest_frames
    log.info("%s %d rest frames", doing, n)
    frames: list[np.ndarray] = []
    while len(frames) < n:
        captured = camera.read(config.camera.timeout_s)
        if captured is None:
            raise CameraError("camera ended before the rest frames were captured")
        frames.append(captured.frame.copy())
    return frames


def _calibrate(sensor: BoardSensor, rest: list[np.ndarray], pixel_format: str) -> CalibrationBundle:
    """The fiber map of ``sensor`` from its camera's rest frames, as its board config says
    (:func:`~optitac_edge.calibration.sensor.calibrate_sensor`)."""
    from optitac_edge.calibration.sensor import calibrate_sensor

    cal = sensor.calibration
    layout = load_layout_csv(cal.layout_path) if cal.layout_path is not None else None
    return calibrate_sensor(rest, pixel_format, sensor.region, layout=layout, rotation_hint_deg=cal.rotation_deg,
                            mirror=cal.mirror)


def fiber_finder(config: BoardConfig) -> Callable[[np.ndarray, str], FiberTable]:
    """How a recording of the board's only (or selected) sensor finds its fibers in its rest frames, to keep
    each fiber's light (``--storage fibers``): as :func:`~optitac_edge.calibration.sensor.calibrate_sensor`
    does, so a bundle calibrated from the recording's rest frames has the very pixel groups the recording
    kept."""
    sensor = config.for_sensor(config.selected).sensors[0]

    def find(rest: np.ndarray, pixel_format: str) -> FiberTable:
        return _calibrate(sensor, list(rest), pixel_format).fibers

    return find


def calibrate_from_camera(config: BoardConfig, camera: Camera,
                          led: LedRing | NoLed | None = None) -> CalibrationBundle:
    """The fiber map of the board's only sensor from ``calibration.rest_frames`` frames of ``camera``."""
    one = config.for_sensor(config.selected)
    return _calibrate(one.sensors[0], read_rest_frames(one, camera, led), camera.pixel_format)


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
