"""A fake OpenCV for the v4l2 backend: ``VideoCapture`` over simulated V4L2 devices.

Everything but the capture comes from the real ``cv2`` (constants,
``VideoWriter.fourcc``); :class:`VideoCapture` follows the real V4L2 backend:
``VideoCapture(index_or_path, apiPreference)``, ``isOpened()``, ``set(prop,
value) -> bool``, ``get(prop) -> float``, ``grab() -> bool`` (blocks until the
next frame), ``retrieve(image=None, flag=0) -> (bool, ndarray)`` (writes into
``image`` when it has the right shape and type), ``read()``, ``release()``.
With ``CAP_PROP_CONVERT_RGB`` = 0 a YUYV device delivers (H, W, 2) and a GREY
device (H, W); with it on, (H, W, 3) BGR. ``CAP_PROP_EXPOSURE`` is refused
unless ``CAP_PROP_AUTO_EXPOSURE`` is 1 (manual), as UVC does.
``CAP_PROP_POS_MSEC`` is the buffer's CLOCK_MONOTONIC timestamp.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import cv2 as _cv2
import numpy as np

_NAMES = [n for n in dir(_cv2) if n.startswith(("CAP_", "COLOR_"))]
globals().update({n: getattr(_cv2, n) for n in _NAMES})
VideoWriter = _cv2.VideoWriter  # for VideoWriter.fourcc
cvtColor = _cv2.cvtColor

BUILD_GSTREAMER = False


def getBuildInformation() -> str:
    return f"  Video I/O:\n    GStreamer:                   {'YES (1.20.3)' if BUILD_GSTREAMER else 'NO'}\n"


def _fourcc(s: str) -> int:
    return int(_cv2.VideoWriter.fourcc(*s))


@dataclass
class FakeDevice:
    """A simulated camera at ``path`` (also reachable as ``/dev/video<index>``)."""

    path: str = "/dev/video0"
    formats: tuple[str, ...] = ("YUYV", "GREY")
    sizes: tuple[tuple[int, int], ...] = ((640, 480), (160, 120), (96, 64))
    fps: float = 200.0
    stall: bool = False  # grab() blocks
    unplugged: bool = False  # grab() fails
    drop_next: int = 0  # the driver loses frames (timestamps jump)
    driver_clock: str = "monotonic"  # "monotonic" or "realtime" (POS_MSEC on another clock)
    busy: bool = False
    opened: list[VideoCapture] = field(default_factory=list)
    produced: dict[int, np.ndarray] = field(default_factory=dict)  # t_ns -> Y plane


DEVICES: dict[str, FakeDevice] = {}


def add_device(device: FakeDevice) -> FakeDevice:
    DEVICES[device.path] = device
    return device


class VideoCapture:
    def __init__(self, source=None, apiPreference=None, *args) -> None:
        self.api = apiPreference
        self.source = source
        self.released = False
        self.release_calls = 0
        self.set_log: list[tuple[int, float]] = []
        if apiPreference == CAP_GSTREAMER:  # noqa: F821
            # a pipeline opens when GStreamer is built in and a "gstreamer" device exists
            key = "gstreamer" if BUILD_GSTREAMER and "appsink" in str(source) else None
        else:
            key = f"/dev/video{source}" if isinstance(source, int) else source
        self.dev = DEVICES.get(key) if key else None
        self._open = self.dev is not None and not self.dev.busy and apiPreference in (CAP_V4L2, CAP_GSTREAMER)  # noqa: F821
        if self._open:
            self.dev.opened.append(self)
        self.fourcc = self.dev.formats[0] if self._open else "YUYV"
        self.width, self.height = (640, 480)
        self.fps = 30.0
        self.convert_rgb = 1.0
        self.auto_exposure = 3.0
        self.exposure = 157.0
        self.gain = 0.0
        self.buffersize = 4.0
        self._n = 0
        self._next_ns: int | None = None
        self._frame: np.ndarray | None = None
        self._t_ns = 0
        self.lock = threading.Lock()

    def isOpened(self) -> bool:
        return self._open and not self.released

    def getBackendName(self) -> str:
        return "V4L2"

    def set(self, prop: int, value: float) -> bool:
        self.set_log.append((prop, value))
        if not self.isOpened():
            return False
        if prop == CAP_PROP_FOURCC:  # noqa: F821
            s = "".join(chr((int(value) >> (8 * i)) & 0xFF) for i in range(4))
            if s not in self.dev.formats:
                return False
            self.fourcc = s
        elif prop in (CAP_PROP_FRAME_WIDTH, CAP_PROP_FRAME_HEIGHT):  # noqa: F821
            want = (int(value), self.height) if prop == CAP_PROP_FRAME_WIDTH else (self.width, int(value))  # noqa: F821
            # the driver snaps to the nearest supported size (and reports success)
            best = min(self.dev.sizes, key=lambda s: abs(s[0] - want[0]) + abs(s[1] - want[1]))
            self.width, self.height = best
        elif prop == CAP_PROP_FPS:  # noqa: F821
            self.fps = min(float(value), self.dev.fps)
        elif prop == CAP_PROP_CONVERT_RGB:  # noqa: F821
            self.convert_rgb = float(value)
        elif prop == CAP_PROP_AUTO_EXPOSURE:  # noqa: F821
            if value not in (1, 3):
                return False
            self.auto_exposure = float(value)
        elif prop == CAP_PROP_EXPOSURE:  # noqa: F821
            if self.auto_exposure != 1:
                return False  # EACCES: exposure_absolute is inactive in auto mode
            self.exposure = float(value)
        elif prop == CAP_PROP_GAIN:  # noqa: F821
            self.gain = float(value)
        elif prop == CAP_PROP_BUFFERSIZE:  # noqa: F821
            self.buffersize = float(value)
        else:
            return False
        return True

    def get(self, prop: int) -> float:
        if not self.isOpened():
            return 0.0
        return {
            CAP_PROP_FOURCC: float(_fourcc(self.fourcc)),  # noqa: F821
            CAP_PROP_FRAME_WIDTH: float(self.width),  # noqa: F821
            CAP_PROP_FRAME_HEIGHT: float(self.height),  # noqa: F821
            CAP_PROP_FPS: float(self.fps),  # noqa: F821
            CAP_PROP_CONVERT_RGB: self.convert_rgb,  # noqa: F821
            CAP_PROP_AUTO_EXPOSURE: self.auto_exposure,  # noqa: F821
            CAP_PROP_EXPOSURE: self.exposure,  # noqa: F821
            CAP_PROP_GAIN: self.gain,  # noqa: F821
            CAP_PROP_BUFFERSIZE: self.buffersize,  # noqa: F821
            CAP_PROP_POS_MSEC: self._pos_msec(),  # noqa: F821
        }.get(prop, 0.0)

    def _pos_msec(self) -> float:
        if self._frame is None:
            return 0.0
        t = self._t_ns if self.dev.driver_clock == "monotonic" else self._t_ns + 1_700_000_000_000_000_000
        return t / 1e6

    def grab(self) -> bool:
        if not self.isOpened():
            return False
        period = int(1e9 / self.fps)
        if self._next_ns is None:
            self._next_ns = time.monotonic_ns() + period
        while True:
            if self.dev.unplugged or self.released:
                time.sleep(0.001)
                return False
            delay = (self._next_ns - time.monotonic_ns()) / 1e9
            if delay > 0:
                time.sleep(min(delay, 0.01))
                continue
            if self.dev.stall:
                self._next_ns += period
                continue
            if self.dev.drop_next > 0:
                self.dev.drop_next -= 1
                self._n += 1
                self._next_ns += period
                continue
            break
        t = self._next_ns // 1000 * 1000  # a V4L2 buffer's timestamp is a timeval (microseconds)
        self._next_ns += period
        h, w = self.height, self.width
        y = ((np.arange(h)[:, None] * 5 + np.arange(w)[None, :] + self._n * 3) % 253).astype(np.uint8)
        if self.fourcc == "YUYV":
            frame = np.empty((h, w, 2), np.uint8)
            frame[:, :, 0] = y
            frame[:, :, 1] = 128
        else:
            frame = y
        self._n += 1
        self._frame, self._t_ns = frame, t
        self.dev.produced[t] = y
        return True

    def retrieve(self, image=None, flag: int = 0):
        if self._frame is None or not self.isOpened():
            return False, None
        out = self._frame
        if self.convert_rgb and self.api != CAP_GSTREAMER:  # noqa: F821  (appsink GRAY8 stays 1-channel)
            if out.ndim == 3:
                out = _cv2.cvtColor(out, _cv2.COLOR_YUV2BGR_YUYV)
            else:
                out = _cv2.cvtColor(out, _cv2.COLOR_GRAY2BGR)
        if image is not None and image.shape == out.shape and image.dtype == out.dtype:
            np.copyto(image, out)
            return True, image
        return True, out.copy()

    def read(self, image=None):
        if not self.grab():
            return False, None
        return self.retrieve(image)

    def release(self) -> None:
        self.release_calls += 1
        self.released = True
