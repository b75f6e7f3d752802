"""The service: camera -> pipeline -> link to the MCU, the one loop that does I/O.

Everything it computes comes from :class:`~optitac_edge.pipeline.Pipeline`
(pure computation on a frame and its timestamp); this module reads the
camera, sends the messages, answers the MCU's commands, sends STATUS about
once a second and keeps systemd informed (READY after the first processed
frame, WATCHDOG from the frame loop itself). It never logs per frame.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .board_config import BoardConfig
from .bundle import CalibrationBundle
from .cameras import Camera, open_camera
from .contact import ContactEstimate
from .errors import CameraError, OptiTacError
from .messages import Command, CommandType, ContactMessage, StatusMessage
from .sdnotify import Notifier
from .transports import Transport

log = logging.getLogger(__name__)

#: Consecutive camera failures after which the service gives up (systemd restarts it).
MAX_CAMERA_FAILURES = 50
#: SET_THRESHOLD unit: the contact-on level in 1e-4 of the rest light (relative signal).
THRESHOLD_UNIT = 1e-4


def camera_kwargs(config: BoardConfig) -> dict[str, Any]:
    """Constructor arguments of the configured camera backend."""
    cam = config.camera
    if cam.backend == "sim":
        return {"fps": cam.fps, "width": cam.width, "height": cam.height, "rgb": cam.pixel_format == "rgb",
                "rest_frames": max(config.calibration.rest_frames, 10), **dict(cam.options)}
    if cam.backend == "recording":
        return {"path": cam.recording, "realtime": True, **dict(cam.options)}
    if cam.backend == "picamera2":
        return {"width": cam.width, "height": cam.height, "fps": cam.fps, "camera_num": cam.index,
                "pixel_format": cam.pixel_format, "exposure_us": cam.exposure_us or None,
                "analogue_gain": cam.gain or None, "warmup_frames": cam.warmup_frames,
                "timeout_s": cam.timeout_s, **dict(cam.options)}
    if cam.backend == "v4l2":  # exposure in driver units goes in camera.options.exposure
        source = {"pipeline": cam.pipeline} if cam.pipeline else {"device": cam.device}
        return {**source, "width": cam.width, "height": cam.height, "fps": cam.fps,
                "gain": cam.gain or None, **dict(cam.options)}
    return dict(cam.options)


def open_board_camera(config: BoardConfig) -> Camera:
    return open_camera(config.camera.backend, **camera_kwargs(config))


def open_board_transport(config: BoardConfig) -> Transport:
    from .transports import open_transport

    link = config.link
    if link.transport == "serial":
        return open_transport("serial", url=link.serial_url, baudrate=link.baudrate, sensor_id=config.sensor.id)
    if link.transport == "can":
        return open_transport("can", channel=link.can_channel, interface=link.can_interface,
                              sensor_id=config.sensor.id,
                              bitrate=link.can_bitrate if link.can_interface == "socketcan" else None)
    return open_transport("null")


def cpu_temperature_c() -> float | None:
    """SoC temperature from sysfs (Pi and Jetson), °C, or None."""
    for zone in sorted(Path("/sys/class/thermal").glob("thermal_zone*/temp")):
        try:
            return int(zone.read_text().strip()) / 1000.0
        except (OSError, ValueError):
            continue
    return None


@dataclass
class ServiceStats:
    """Counters of one run."""

    frames: int = 0
    contacts: int = 0
    sent: int = 0
    frames_dropped: int = 0
    camera_errors: int = 0
    commands: dict[str, int] = field(default_factory=dict)
    started_ns: int = 0

    def fps(self, now_ns: int) -> float:
        elapsed = (now_ns - self.started_ns) / 1e9
        return self.frames / elapsed if elapsed > 0 else 0.0


class Service:
    """Runs the frame loop with one camera, one pipeline and one transport (all opened by the caller)."""

    def __init__(self, config: BoardConfig, bundle: CalibrationBundle, camera: Camera, transport: Transport,
                 notifier: Notifier | None = None) -> None:
        from .pipeline import Pipeline

        bundle.fibers.check_frame(np.zeros(camera.frame_shape, np.uint8), camera.pixel_format)
        self.config = config
        self.bundle = bundle
        self.camera = camera
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
        s.fps_x10 = int(round(st.fps(now_ns) * 10))
        s.frames_dropped = st.frames_dropped
        s.camera_errors = st.camera_errors
        c = self.transport.counters
        s.link_errors = c.send_errors + c.rx_errors
        temp = cpu_temperature_c()
        s.cpu_temp_c_x10 = -32768 if temp is None else int(round(temp * 10))
        s.state = ((1 if self.streaming else 0) | (2 if self.pipeline.baseline_ready else 0)
                   | (4 if self._degraded else 0) | (8 if st.camera_errors else 0))
        return s

    # -- the loop ----------------------------------------------------------------------------

    def run(self, stop: threading.Event, duration_s: float | None = None,
            on_result: Callable[[ContactEstimate, ServiceStats], None] | None = None) -> ServiceStats:
        """Process frames until ``stop`` is set, ``duration_s`` passes or a finite source ends."""
        st = self.stats
        st.started_ns = time.monotonic_ns()
        end_ns = None if duration_s is None else st.started_ns + int(duration_s * 1e9)
        period_ns = int(self.config.status.period_s * 1e9)
        next_status = st.started_ns + period_ns
        timeout = self.config.camera.timeout_s
        last_seq: int | None = None
        failures = 0
        ready = False
        while not stop.is_set():
            now_ns = time.monotonic_ns()
            if end_ns is not None and now_ns >= end_ns:
                break
            try:
                captured = self.camera.read(timeout)
            except CameraError as exc:
                st.camera_errors += 1
                failures += 1
                if failures == 1 or failures % 10 == 0:
                    log.warning("camera error %d: %s", st.camera_errors, exc)
                if failures >= MAX_CAMERA_FAILURES:
                    raise
                continue
            if captured is None:
                break
            failures = 0
            if last_seq is not None and captured.seq > last_seq + 1:
                st.frames_dropped += captured.seq - last_seq - 1
            last_seq = captured.seq
            est = self.pipeline.process(captured.frame, captured.t_ns)
            st.frames += 1
            st.contacts += int(est.contact)
            if self.streaming and st.frames % self.rate_divider == 0:
                self._message.fill(est, captured.t_ns, time.monotonic_ns(), self.pipeline.calibrated,
                                   degraded=self._degraded)
                self.transport.send_contact(self._message)
                st.sent += 1
            if not ready:
                ready = True
                self.notifier.ready("processing frames")
                log.info("first frame processed; streaming to the MCU")
            self.notifier.watchdog()
            for command in self.transport.poll_commands():
                self.handle(command)
            if on_result is not None:
                on_result(est, st)
            now_ns = time.monotonic_ns()
            if now_ns >= next_status:
                next_status = now_ns + period_ns
                self.transport.send_status(self.status_message(now_ns))
        self.notifier.stopping()
        log.info("stopped after %d frames (%d contacts, %d dropped, %d camera errors)",
                 st.frames, st.contacts, st.frames_dropped, st.camera_errors)
        return st


def adjust_led(config: BoardConfig, camera: Camera, led: Any) -> float:
    """Lower the LED ring until the brightest fibers stay below saturation; returns the brightness.

    Each trial sets the brightness, lets two frames expose, and takes the
    ``led.peak_percentile`` of the third frame's gray levels.
    """
    from .frames import to_gray
    from .led import adjust_brightness_for_saturation, fiber_peak

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
                      led: Any = None) -> CalibrationBundle:
    """The calibration bundle: loaded if it exists, else calibrated from the camera's rest frames.

    With an LED ring (``led``) and ``led.adjust_at_calibration``, its brightness
    is first lowered until no fiber saturates.
    """
    from .bundle import load_bundle, save_bundle
    from .calibration import calibrate_fibers
    from .layout import load_layout_csv

    path = cal_path if cal_path is not None else config.calibration.bundle_path
    if path is not None and Path(path).exists():
        return load_bundle(path)
    if path is not None and cal_path is not None:
        from .errors import BundleError

        raise BundleError(f"{path}: calibration bundle not found")
    if config.calibration.if_missing == "fail":
        raise OptiTacError(f"no calibration bundle at {path} and calibration.if_missing = 'fail'")
    if led is not None and config.led.enabled and config.led.adjust_at_calibration:
        adjust_led(config, camera, led)
    n = config.calibration.rest_frames
    log.info("calibrating the fiber map from %d rest frames", n)
    frames = []
    while len(frames) < n:
        captured = camera.read(config.camera.timeout_s)
        if captured is None:
            raise CameraError("camera ended before the rest frames were captured")
        frames.append(captured.frame.copy())
    layout = load_layout_csv(config.calibration.layout_path) if config.calibration.layout else None
    bundle = calibrate_fibers(frames, camera.pixel_format, layout=layout,
                              rotation_hint_deg=config.calibration.rotation_deg, mirror=config.calibration.mirror)
    if path is not None:
        bundle = save_bundle(bundle, path)
        log.info("saved the calibration bundle to %s", path)
    return bundle
