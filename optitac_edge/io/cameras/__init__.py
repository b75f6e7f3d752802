"""Camera backends behind one small interface, chosen by name, imported only when used.

>>> with open_camera("sim", fps=60) as cam:       # doctest: +SKIP
...     captured = cam.read()

Importing this package needs the standard library only (the board config
validates backend names, queue depths and the ``[camera]`` section with it,
before anything is installed); :class:`Camera` and :class:`CapturedFrame` are
loaded on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from optitac_edge.errors import CameraError
from optitac_edge.io.cameras.section import MAX_QUEUE_FRAMES, CameraConfig
from optitac_edge.io.registry import Registry

if TYPE_CHECKING:
    from optitac_edge.io.cameras.base import Camera, CapturedFrame

#: Backend name -> its class, imported on first use (python-can style): io's own, then those other packages
#: (and layers: the simulator its ``sim``) add through the ``optitac_edge.cameras`` entry point group.
CAMERAS: Registry[Camera] = Registry("camera backend", CameraError, {
    "recording": "optitac_edge.io.cameras.recording:RecordingCamera",
    "picamera2": "optitac_edge.io.cameras.picamera2:Picamera2Camera",
    "v4l2": "optitac_edge.io.cameras.v4l2:V4L2Camera",
}, group="optitac_edge.cameras")


def open_camera(name: str, **kwargs: Any) -> Camera:
    """Open the camera backend called ``name`` with backend-specific ``kwargs``.

    Raises
    ------
    CameraError
        If no backend has that name or the backend cannot be opened.
    """
    return CAMERAS.make(name, **kwargs)


def __getattr__(name: str) -> Any:
    if name in ("Camera", "CapturedFrame"):
        from optitac_edge.io.cameras import base

        return getattr(base, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["CAMERAS", "MAX_QUEUE_FRAMES", "Camera", "CameraConfig", "CapturedFrame", "open_camera"]
