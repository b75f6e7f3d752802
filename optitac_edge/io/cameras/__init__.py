"""Camera backends behind one small interface, chosen by name, imported only when used.

>>> with open_camera("sim", fps=60) as cam:       # doctest: +SKIP
...     captured = cam.read()
"""

from __future__ import annotations

from typing import Any

from optitac_edge.io.cameras.base import Camera, CapturedFrame

#: Backend name -> "module:class", imported on first use (python-can style).
BACKENDS: dict[str, str] = {
    "sim": "optitac_edge.sim.camera:SimCamera",
    "recording": "optitac_edge.io.cameras.recording:RecordingCamera",
    "picamera2": "optitac_edge.io.cameras.picamera2:Picamera2Camera",
    "v4l2": "optitac_edge.io.cameras.v4l2:V4L2Camera",
}


def open_camera(name: str, **kwargs: Any) -> Camera:
    """Open the camera backend called ``name`` with backend-specific ``kwargs``.

    Raises
    ------
    CameraError
        If no backend has that name or the backend cannot be opened.
    """
    from optitac_edge.errors import CameraError
    from optitac_edge.io.device import load_backend

    return load_backend(BACKENDS, name, "camera backend", CameraError)(**kwargs)


__all__ = ["BACKENDS", "Camera", "CapturedFrame", "open_camera"]
