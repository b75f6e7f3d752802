"""V4L2 cameras (USB/UVC, Jetson) and Jetson CSI cameras (GStreamer), through OpenCV.

A grab thread owns the ``cv2.VideoCapture``: it grabs continuously, so the
driver's queue never fills, and publishes each frame (with its timestamp and
sequence number) into a :class:`~.frame_ring.FrameRing`. Up to
``queue_frames`` frames wait for :meth:`read`, which returns the oldest; when
one more comes the oldest waiting frame is dropped (counted in
:attr:`V4L2Camera.overwritten`, and a gap in ``seq``). The ring's
``queue_frames + 2`` buffers are preallocated, and the frame a caller holds is
never written until its next read.

Frames are gray (H, W): a ``GREY`` device delivers them as they are, a
``YUYV`` device is read raw (``CAP_PROP_CONVERT_RGB`` = 0, (H, W, 2)) and its
Y channel kept. See docs/cameras.md.
"""

from __future__ import annotations

import glob
import logging
import os
import re
import threading
import time
from fractions import Fraction
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from optitac_edge.errors import CameraError
from optitac_edge.io.cameras.base import Camera, CapturedFrame
from optitac_edge.io.cameras.frame_ring import FrameRing
from optitac_edge.io.threads import NamedThread

if TYPE_CHECKING:
    from optitac_edge.io.cameras.section import CameraConfig
    from optitac_edge.io.device import BoardView

log = logging.getLogger(__name__)

_V4L2_EXPOSURE_MANUAL = 1  # V4L2_EXPOSURE_MANUAL, what CAP_PROP_AUTO_EXPOSURE takes (unnormalised)
_V4L2_EXPOSURE_AUTO = 3  # V4L2_EXPOSURE_APERTURE_PRIORITY (UVC auto)
_FAIL_LIMIT = 20  # consecutive failed grabs before the device counts as gone


def msec_to_ns(msec: float) -> int:
    """A driver timestamp in milliseconds (``CAP_PROP_POS_MSEC``) as integer nanoseconds.

    A V4L2 buffer's timestamp is a ``timeval`` (whole microseconds), so it is
    rounded to the microsecond: exact for any uptime, where ``int(msec * 1e6)``
    fell a nanosecond short for about one timestamp in seventy.
    """
    return round(msec * 1e3) * 1000


def fourcc_code(fourcc: str) -> int:
    return int(cv2.VideoWriter.fourcc(*fourcc))


def fourcc_str(value: float) -> str:
    code = int(value)
    return "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4))


def has_gstreamer() -> bool:
    """Whether this OpenCV build can open GStreamer pipelines."""
    match = re.search(r"GStreamer:\s*(\w+)", cv2.getBuildInformation())
    return bool(match and match.group(1).upper() == "YES")


def argus_pipeline(width: int, height: int, fps: float, sensor_id: int = 0,
                   exposure_ns: int | None = None, gain: float | None = None) -> str:
    """GStreamer pipeline for a Jetson CSI camera: nvarguscamerasrc → GRAY8 appsink.

    With ``exposure_ns``/``gain`` the ranges are pinned (manual exposure); AE
    and AWB are locked and the ISP digital gain fixed at 1 either way.
    """
    rate = Fraction(fps).limit_denominator(1001)
    src = [f"nvarguscamerasrc sensor-id={sensor_id}", "aelock=true", "awblock=true",
           'ispdigitalgainrange="1 1"']
    if exposure_ns is not None:
        src.append(f'exposuretimerange="{int(exposure_ns)} {int(exposure_ns)}"')
    if gain is not None:
        src.append(f'gainrange="{gain:g} {gain:g}"')
    return (" ".join(src)
            + f" ! video/x-raw(memory:NVMM),width={width},height={height},"
              f"framerate={rate.numerator}/{rate.denominator},format=NV12"
            + " ! nvvidconv ! video/x-raw,format=GRAY8"
            + " ! appsink drop=1 max-buffers=1 sync=false")


def _resolve_device(device: int | str) -> int | str:
    """An index, or the device node behind a path (``/dev/v4l/by-id/...`` symlinks)."""
    if isinstance(device, int):
        return device
    if str(device).isdigit():
        return int(device)
    path = str(device)
    if not os.path.exists(path):
        known = sorted(glob.glob("/dev/v4l/by-id/*")) or sorted(glob.glob("/dev/video*"))
        raise CameraError(f"v4l2: no such camera device {path!r} (present: {', '.join(known) or 'none'})")
    return os.path.realpath(path)


class V4L2Camera(Camera):
    """A V4L2 device, or a GStreamer pipeline, read through OpenCV.

    Parameters
    ----------
    device : int or str
        Device index, ``/dev/videoN`` or, preferably, a stable
        ``/dev/v4l/by-id/...`` / ``/dev/v4l/by-path/...`` link.
    width, height : int
        Frame size; the device must deliver exactly this size.
    fps : float
        Frame rate requested from the driver (the driver's answer is kept).
    fourcc : {"GREY", "YUYV"}
        Pixel format requested from the device; both deliver gray frames.
    exposure : float, optional
        Manual exposure in the driver's units (UVC ``exposure_time_absolute``:
        100 µs); auto exposure is switched off. ``None`` leaves the device's
        exposure mode alone.
    gain : float, optional
        Manual gain in the driver's units.
    buffers : int, optional
        Driver buffers (``CAP_PROP_BUFFERSIZE``).
    timestamps : {"auto", "driver", "grab"}
        ``driver``: the V4L2 buffer timestamp (``CAP_PROP_POS_MSEC``, CLOCK_MONOTONIC
        on UVC and most drivers); ``grab``: CLOCK_MONOTONIC when ``grab()``
        returned; ``auto``: the driver's if it is on this clock, else grab time.
    pipeline : str, optional
        A GStreamer pipeline ending in a GRAY8 ``appsink`` (opened with
        ``CAP_GSTREAMER``) instead of a V4L2 device.
    csi : bool
        Build the pipeline for a Jetson CSI camera (:func:`argus_pipeline`)
        from ``sensor_id``, size, fps, ``exposure_ns`` and ``gain``.
    sensor_id : int
        ``nvarguscamerasrc sensor-id`` when ``csi``.
    exposure_ns : int, optional
        Fixed exposure for the CSI pipeline, nanoseconds.
    open_timeout_s : float
        Time the first frame may take after opening.
    queue_frames : int
        Frames that may wait for :meth:`read` (1..16); when one more comes the
        oldest is dropped. 1 keeps only the latest frame.
    """

    reuses_buffer = True

    @classmethod
    def section_kwargs(cls, section: CameraConfig, board: BoardView) -> dict[str, Any]:
        """``[camera]`` device or pipeline, width, height, fps, gain, queue_frames (exposure in driver units
        goes in ``camera.options.exposure``)."""
        c = section
        source = {"pipeline": c.pipeline} if c.pipeline else {"device": c.device}
        return {**source, "width": c.width, "height": c.height, "fps": c.fps, "gain": c.gain or None,
                "queue_frames": c.queue_frames}

    def __init__(  # noqa: PLR0913
        self,
        device: int | str = 0,
        width: int = 640,
        height: int = 480,
        fps: float = 60.0,
        fourcc: str = "GREY",
        exposure: float | None = None,
        gain: float | None = None,
        buffers: int | None = None,
        timestamps: str = "auto",
        pipeline: str | None = None,
        csi: bool = False,
        sensor_id: int = 0,
        exposure_ns: int | None = None,
        open_timeout_s: float = 3.0,
        queue_frames: int = 4,
    ) -> None:
        super().__init__()
        if fourcc not in ("GREY", "YUYV"):
            raise CameraError(f"v4l2: fourcc must be 'GREY' or 'YUYV', not {fourcc!r}")
        if timestamps not in ("auto", "driver", "grab"):
            raise CameraError(f"v4l2: timestamps must be 'auto', 'driver' or 'grab', not {timestamps!r}")
        if width <= 0 or height <= 0 or not fps > 0:
            raise CameraError(f"v4l2: bad size or rate {width}x{height} at {fps} fps")
        self.pixel_format = "gray"
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        # before the device is opened: a bad queue_frames raises without touching it
        self._ring = FrameRing((self.height, self.width), queue_frames)
        self.fourcc = fourcc
        self._timestamps = timestamps
        if csi and pipeline is None:
            pipeline = argus_pipeline(self.width, self.height, self.fps, sensor_id, exposure_ns, gain)
        self.pipeline = pipeline
        self.source = pipeline if pipeline is not None else device
        if pipeline is not None:
            self._timestamps = "grab"  # appsink PTS are stream time, not CLOCK_MONOTONIC
            self._cap = self._open_gstreamer(pipeline)
        else:
            self._cap = self._open_v4l2(_resolve_device(device), fourcc, exposure, gain, buffers)

        self._raw = np.empty((self.height, self.width, 2), np.uint8) if fourcc == "YUYV" and pipeline is None \
            else None
        self._stop = threading.Event()
        self._thread = NamedThread(target=self._grab_loop, name="v4l2-grab", daemon=True)
        self._thread.start()
        try:  # the first frame proves the device streams in the promised format
            if not self._ring.wait_first(open_timeout_s):
                raise CameraError(f"v4l2: {self.source!r} delivered no frame within {open_timeout_s:g} s")
            if self._ring.error is not None:
                raise CameraError(self._ring.error)
        except BaseException:
            self._close_internal()
            raise

    @property
    def overwritten(self) -> int:
        """Frames dropped from the queue because ``queue_frames`` newer ones were waiting."""
        return self._ring.overwritten

    # -- opening -------------------------------------------------------------

    def _open_v4l2(self, device: int | str, fourcc: str, exposure: float | None, gain: float | None,
                   buffers: int | None) -> Any:
        cap = cv2.VideoCapture(device, cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise CameraError(f"v4l2: cannot open {self.source!r} (missing, busy, or no permission "
                              "— is the user in the 'video' group?)")
        try:
            # Format first: changing it resets the stream and with it size and rate.
            settings: list[tuple[str, int, float, bool]] = [
                ("FOURCC", cv2.CAP_PROP_FOURCC, fourcc_code(fourcc), True),
                ("FRAME_WIDTH", cv2.CAP_PROP_FRAME_WIDTH, self.width, True),
                ("FRAME_HEIGHT", cv2.CAP_PROP_FRAME_HEIGHT, self.height, True),
                ("FPS", cv2.CAP_PROP_FPS, self.fps, False),
                ("CONVERT_RGB", cv2.CAP_PROP_CONVERT_RGB, 0, True),
            ]
            if buffers is not None:
                settings.append(("BUFFERSIZE", cv2.CAP_PROP_BUFFERSIZE, buffers, False))
            if exposure is not None:
                settings.append(("AUTO_EXPOSURE", cv2.CAP_PROP_AUTO_EXPOSURE, _V4L2_EXPOSURE_MANUAL, True))
                settings.append(("EXPOSURE", cv2.CAP_PROP_EXPOSURE, exposure, True))
            if gain is not None:
                settings.append(("GAIN", cv2.CAP_PROP_GAIN, gain, True))
            for name, prop, value, required in settings:
                if not cap.set(prop, value):
                    if required:
                        raise CameraError(f"v4l2: {self.source!r} refused CAP_PROP_{name} = {value:g}")
                    log.warning("v4l2: %r refused CAP_PROP_%s = %g", self.source, name, value)
            got_fourcc = fourcc_str(cap.get(cv2.CAP_PROP_FOURCC))
            if got_fourcc != fourcc:
                raise CameraError(f"v4l2: {self.source!r} delivers {got_fourcc!r}, not {fourcc!r} "
                                  "(see v4l2-ctl --list-formats-ext)")
            got = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
            if got != (self.width, self.height):
                raise CameraError(f"v4l2: {self.source!r} delivers {got[0]}x{got[1]} {fourcc}, not the "
                                  f"requested {self.width}x{self.height}")
            fps = float(cap.get(cv2.CAP_PROP_FPS))
            if fps > 0 and abs(fps - self.fps) > 0.01 * self.fps:
                log.warning("v4l2: %r runs at %g fps, not the requested %g", self.source, fps, self.fps)
                self.fps = fps
            if exposure is not None:
                got_exp = float(cap.get(cv2.CAP_PROP_EXPOSURE))
                if abs(got_exp - exposure) > max(1e-6, 0.01 * abs(exposure)):
                    log.warning("v4l2: %r set exposure %g, reads back %g", self.source, exposure, got_exp)
        except BaseException:
            cap.release()
            raise
        #: Settings read back from the driver after opening (for the recording's metadata).
        self.settings = {"fourcc": fourcc, "width": self.width, "height": self.height, "fps": self.fps,
                         "exposure": None if exposure is None else float(cap.get(cv2.CAP_PROP_EXPOSURE)),
                         "gain": None if gain is None else float(cap.get(cv2.CAP_PROP_GAIN))}
        return cap

    def _open_gstreamer(self, pipeline: str) -> Any:
        if not has_gstreamer():
            raise CameraError("v4l2: this OpenCV has no GStreamer support (cv2.getBuildInformation() "
                              "shows 'GStreamer: NO'); on a Jetson use the system OpenCV "
                              "(python3-opencv from JetPack) instead of opencv-python from PyPI")
        cap = cv2.VideoCapture(pipeline, cv2.CAP_GSTREAMER)
        if not cap.isOpened():
            cap.release()
            raise CameraError(f"v4l2: cannot start the GStreamer pipeline {pipeline!r}")
        self.settings = {"pipeline": pipeline, "width": self.width, "height": self.height, "fps": self.fps}
        return cap

    # -- grab thread ---------------------------------------------------------

    def _grab_loop(self) -> None:
        cap, ring, period_ns = self._cap, self._ring, 1e9 / self.fps
        failures, seq, last_t = 0, 0, None
        use_driver: bool | None = {"driver": True, "grab": False}.get(self._timestamps)
        try:
            while not self._stop.is_set():
                ok = cap.grab()
                now = time.monotonic_ns()
                if self._stop.is_set():
                    break
                if not ok:
                    failures += 1
                    if failures >= _FAIL_LIMIT:
                        ring.fail(f"v4l2: {self.source!r} stopped delivering frames (unplugged?)")
                        return
                    time.sleep(0.005)
                    continue
                back = ring.back
                if self._raw is not None:
                    ok, img = cap.retrieve(self._raw)
                else:
                    ok, img = cap.retrieve(back)
                if not ok or img is None:
                    failures += 1
                    continue
                failures = 0
                if img.ndim == 3 and img.shape[2] == 1:
                    img = img[:, :, 0]
                src = img[:, :, 0] if self._raw is not None else img
                if src.shape != back.shape or src.dtype != np.uint8:
                    ring.fail(f"v4l2: {self.source!r} delivered {src.dtype} {img.shape}, "
                              f"expected {self.fourcc} {self.width}x{self.height}")
                    return
                if not np.shares_memory(src, back):
                    np.copyto(back, src)
                t = now
                if use_driver is not False:
                    driver_ns = msec_to_ns(cap.get(cv2.CAP_PROP_POS_MSEC))
                    if use_driver is None:  # auto: trust it if it is on CLOCK_MONOTONIC
                        use_driver = driver_ns > 0 and abs(now - driver_ns) < 1_000_000_000
                        log.info("v4l2: %r timestamps from %s", self.source, "the driver" if use_driver else "grab()")
                    if use_driver:
                        t = driver_ns
                if last_t is not None and t <= last_t:
                    t = last_t + 1
                seq += 1 if last_t is None or not use_driver else max(1, round((t - last_t) / period_ns))
                last_t = t
                ring.publish(t, seq)
        except Exception as exc:  # noqa: BLE001 - OpenCV errors must not kill the thread silently
            ring.fail(f"v4l2: grab thread failed: {exc}")
        finally:
            cap.release()

    # -- camera interface ----------------------------------------------------

    def _read_internal(self, timeout_s: float) -> CapturedFrame:
        frame, t_ns, seq = self._ring.take(timeout_s, f"v4l2 {self.source!r}")
        return CapturedFrame(frame, t_ns, seq)

    def _close_internal(self) -> None:
        self._stop.set()
        thread = getattr(self, "_thread", None)
        if thread is None:
            return
        # The thread releases the capture itself once grab() returns (never release a
        # VideoCapture another thread is inside); a stuck driver may take a while.
        thread.join(timeout=2.0)
        if thread.is_alive():
            log.warning("v4l2: grab thread of %r still blocked in grab(); it releases the device "
                        "when the driver returns", self.source)
