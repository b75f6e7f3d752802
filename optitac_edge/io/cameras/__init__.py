"""Camera backends behind one small interface, chosen by name, imported only when used.

>>> with open_camera("sim", fps=60) as cam:       # doctest: +SKIP
...     captured = cam.read()

Importing this package needs the standard library only (the board config
validates backend names and queue depths with it, before anything is
installed); :class:`Camera` and :class:`CapturedFrame` are loaded on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from optitac_edge.io.cameras.base import Camera, CapturedFrame

#: Entry point group through which a package adds its cameras (the simulator its ``sim``, from the layer above).
ENTRY_POINTS = "optitac_edge.cameras"


def _registered() -> dict[str, str]:
    """The cameras other packages (and layers) register: ``[project.entry-points."optitac_edge.cameras"]``."""
    from importlib.metadata import entry_points

    return {ep.name: ep.value for ep in entry_points(group=ENTRY_POINTS)}


#: Backend name -> "module:class", imported on first use (python-can style): io's own, then the registered.
BACKENDS: dict[str, str] = {
    "recording": "optitac_edge.io.cameras.recording:RecordingCamera",
    "picamera2": "optitac_edge.io.cameras.picamera2:Picamera2Camera",
    "v4l2": "optitac_edge.io.cameras.v4l2:V4L2Camera",
    **_registered(),
}
#: Most frames a camera may queue for the loop (``camera.queue_frames``).
MAX_QUEUE_FRAMES = 16


def open_camera(name: str, **kwargs: Any) -> Camera:
    """Open the camera backend called ``name`` with backend-specific ``kwargs``.

    Raises
    ------
    CameraError
        If no backend has that name or the backend cannot be opened.
    """
    from optitac_edge.errors import CameraError
    from optitac_edge.io.device import load_backend

    camera: Camera = load_backend(BACKENDS, name, "camera backend", CameraError)(**kwargs)
    return camera


def __getattr__(name: str) -> Any:
    if name in ("Camera", "CapturedFrame"):
        from optitac_edge.io.cameras import base

        return getattr(base, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["BACKENDS", "MAX_QUEUE_FRAMES", "Camera", "CapturedFrame", "open_camera"]
