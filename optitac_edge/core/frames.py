"""Pixel formats of camera frames and their conversion to grayscale.

A frame is a C-contiguous uint8 array in one of these formats:

``gray``   shape (H, W): luminance only (V4L2 GREY, a recording's gray frames).
``rgb``    shape (H, W, 3): red, green, blue.
``yuv420`` shape (H * 3 // 2, W): planar I420 as picamera2 delivers a lores
           stream; the first H rows are the Y (luminance) plane.

Grayscale is the luminance plane: the Y plane as it is for ``yuv420``, and
ITU-R BT.601 weights (0.299 R + 0.587 G + 0.114 B, as OpenCV) for ``rgb``.
"""

from __future__ import annotations

import numpy as np

from optitac_edge.errors import FrameMismatchError

PIXEL_FORMATS: tuple[str, ...] = ("gray", "rgb", "yuv420")


def frame_geometry(shape: tuple[int, ...], pixel_format: str) -> tuple[int, int]:
    """Image height and width of a frame of array shape ``shape``.

    Raises
    ------
    FrameMismatchError
        If ``shape`` is impossible for ``pixel_format``.
    """
    if pixel_format == "gray" and len(shape) == 2:
        return int(shape[0]), int(shape[1])
    if pixel_format == "rgb" and len(shape) == 3 and shape[2] == 3:
        return int(shape[0]), int(shape[1])
    if pixel_format == "yuv420" and len(shape) == 2 and shape[0] % 3 == 0:
        return int(shape[0]) * 2 // 3, int(shape[1])
    raise FrameMismatchError(f"array of shape {tuple(shape)} is not a {pixel_format} frame")


def frame_shape(height: int, width: int, pixel_format: str) -> tuple[int, ...]:
    """The array shape of a ``height`` x ``width`` frame in ``pixel_format`` (the inverse of
    :func:`frame_geometry`)."""
    if pixel_format == "rgb":
        return (height, width, 3)
    if pixel_format == "yuv420":
        return (height * 3 // 2, width)
    return (height, width)


def infer_pixel_format(shape: tuple[int, ...]) -> str:
    """Pixel format of a recording frame: ``gray`` for (H, W), ``rgb`` for (H, W, 3)."""
    if len(shape) == 2:
        return "gray"
    if len(shape) == 3 and shape[2] == 3:
        return "rgb"
    raise FrameMismatchError(f"frames of shape {tuple(shape)} are neither (H,W) gray nor (H,W,3) RGB")


def to_gray(frame: np.ndarray, pixel_format: str) -> np.ndarray:
    """Whole-frame grayscale image, shape (H, W), uint8.

    Used where the whole image is needed (fiber calibration, the reference
    method). The runtime pipeline converts only the fiber pixels instead.
    """
    if pixel_format == "gray":
        return frame
    if pixel_format == "yuv420":
        h, _ = frame_geometry(frame.shape, pixel_format)
        return frame[:h]
    if pixel_format == "rgb":
        import cv2

        return cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY)
    raise FrameMismatchError(f"unknown pixel format {pixel_format!r}")
