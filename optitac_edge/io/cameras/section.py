"""A board's ``[camera]`` (and each ``[cameras.NAME]``): the keys every camera backend reads."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from optitac_edge.fields import Scalar, choice, integer, number, path_text, setting, string

#: Most frames a camera may queue for the loop (``camera.queue_frames``).
MAX_QUEUE_FRAMES = 16


def camera_backend(value: object, from_text: bool) -> str:
    """A name of the camera registry (:data:`optitac_edge.io.cameras.CAMERAS`, the one list of them)."""
    from optitac_edge.io.cameras import CAMERAS

    return choice(*sorted(CAMERAS))(value, from_text)


@dataclass(frozen=True)
class CameraConfig:
    backend: str = setting(camera_backend, "sim", "camera backend: sim, recording, picamera2, v4l2")
    width: int = setting(integer(16, 8192), 640, "image width, px")
    height: int = setting(integer(16, 8192), 480, "image height, px")
    fps: float = setting(number(1, 1000), 60.0, "frame rate, frames/s")
    pixel_format: str = setting(choice("gray", "rgb", "yuv420"), "gray", "pixel format delivered")
    exposure_us: int = setting(integer(0, 10_000_000), 0, "exposure time, µs (0 = automatic)")
    gain: float = setting(number(0, 64), 0.0, "analogue gain (0 = automatic)")
    index: int = setting(integer(0, 15), 0, "picamera2: camera number")
    device: str = setting(path_text, "", "v4l2: device node, best a /dev/v4l/by-id/... path")
    pipeline: str = setting(string(4096), "", "v4l2: a GStreamer pipeline ending in appsink (instead of device)")
    recording: str = setting(path_text, "", "recording: the recording directory to replay")
    warmup_frames: int = setting(integer(0, 1000), 5, "frames discarded after opening (auto exposure settles)")
    timeout_s: float = setting(number(0.001, 60), 1.0, "longest wait for one frame, s (at least 1 ms)")
    queue_frames: int = setting(integer(1, MAX_QUEUE_FRAMES), 4, "frames that may wait for the loop; when full the "
                                "oldest is dropped (1 = latest frame only)")
    #: Backend-specific options (free names, scalar values), validated by the backend.
    options: Mapping[str, Scalar] = field(default_factory=lambda: MappingProxyType({}),
                                          metadata={"doc": "backend-specific options (scalars)"})
