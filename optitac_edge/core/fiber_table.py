"""The fiber lookup table: which image pixels belong to which layout fiber.

Built once at fiber calibration (see :mod:`optitac_edge.calibration.fiber_map`); used every
frame to take each fiber's mean intensity with one gather and one segmented
sum, with no labelling or segmentation per frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from optitac_edge.core.colour import mix_pixels, mix_weights
from optitac_edge.core.frames import PIXEL_FORMATS, frame_geometry, frame_shape
from optitac_edge.errors import FrameMismatchError

#: Bytes per CPU cache line (x86-64, Cortex-A72/A76), for the gather's probe of a new frame.
CACHE_LINE = 64
#: Largest image side a fiber table may be built for, px.
MAX_SIDE = 8192


@dataclass(frozen=True, eq=False)
class FiberTable:
    """Pixels of every layout fiber in the frames a bundle was built for.

    Attributes
    ----------
    height, width : int
        Image size in pixels of the frames the table applies to.
    pixel_format : str
        ``gray``, ``rgb`` or ``yuv420`` (see :mod:`optitac_edge.core.frames`).
    pixel_index : ndarray, shape (P,), int32
        Flat indices (``row * width + col``) into the luminance plane, grouped
        by fiber in layout order.
    pixel_start : ndarray, shape (N + 1,), int64
        Fiber ``i`` owns ``pixel_index[pixel_start[i]:pixel_start[i + 1]]``;
        every fiber owns at least one pixel (dead fibers: pixels at their
        predicted position).
    centroid_px : ndarray, shape (N, 2), float64
        Fiber end-face centres (col, row) in pixels: measured for found
        fibers, predicted from the transform for dead ones.
    dead : ndarray, shape (N,), bool
        Layout fibers not found in the rest frames (dark or broken).
    unmatched_px : ndarray, shape (K, 2), float64
        Centres (col, row) of detected blobs that fit no layout fiber.
    """

    height: int
    width: int
    pixel_format: str
    pixel_index: np.ndarray
    pixel_start: np.ndarray
    centroid_px: np.ndarray
    dead: np.ndarray
    unmatched_px: np.ndarray

    def __post_init__(self) -> None:
        for name in ("height", "width"):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or not 1 <= value <= MAX_SIDE:
                raise ValueError(f"frame {name} must be an integer in 1..{MAX_SIDE}, got {value!r}")
        if self.pixel_format not in PIXEL_FORMATS:
            raise ValueError(f"pixel format must be one of {', '.join(PIXEL_FORMATS)}, got {self.pixel_format!r}")
        if self.centroid_px.ndim != 2 or self.centroid_px.shape[1:] != (2,):
            raise ValueError("fiber centroids must have shape (N, 2)")
        if not np.all(np.isfinite(self.centroid_px)):
            raise ValueError("fiber centroids must be finite")
        if self.dead.dtype != bool:
            raise ValueError("dead must be a boolean array")
        if self.dead.size and self.dead.all():
            raise ValueError("every fiber is dead: the bundle cannot see a contact")
        n = self.centroid_px.shape[0]
        if self.pixel_start.shape != (n + 1,) or self.dead.shape != (n,):
            raise ValueError("fiber table arrays disagree on the number of fibers")
        if np.any(np.diff(self.pixel_start) < 1) or self.pixel_start[-1] != self.pixel_index.size:
            raise ValueError("every fiber needs at least one pixel")
        if self.pixel_index.size and (
            self.pixel_index.min() < 0 or self.pixel_index.max() >= self.height * self.width
        ):
            raise ValueError("fiber pixel index outside the image")

    @property
    def n_fibers(self) -> int:
        return int(self.dead.shape[0])

    @property
    def pixel_count(self) -> np.ndarray:
        """Pixels per fiber, shape (N,), int64."""
        return np.diff(self.pixel_start)

    def label_image(self) -> np.ndarray:
        """Label image, shape (H, W), int32: 0 background, ``i + 1`` for fiber ``i``."""
        labels = np.zeros(self.height * self.width, dtype=np.int32)
        fiber_of_pixel = np.repeat(np.arange(1, self.n_fibers + 1, dtype=np.int32), self.pixel_count)
        labels[self.pixel_index] = fiber_of_pixel
        return labels.reshape(self.height, self.width)

    @property
    def frame_shape(self) -> tuple[int, ...]:
        """The array shape of the frames the table was built for (its pixel format's)."""
        return frame_shape(self.height, self.width, self.pixel_format)

    def check_frame(self, frame: np.ndarray, pixel_format: str) -> None:
        """Raise :class:`FrameMismatchError` unless ``frame`` is what the table was built for."""
        self.check_frame_shape(frame.shape, pixel_format, frame.dtype)

    def check_frame_shape(self, shape: tuple[int, ...], pixel_format: str,
                          dtype: np.dtype[Any] | type = np.uint8) -> None:
        """Raise :class:`FrameMismatchError` unless frames of ``shape``, ``pixel_format`` and
        ``dtype`` are what the table was built for (e.g. a camera's ``frame_shape``)."""
        if pixel_format != self.pixel_format:
            raise FrameMismatchError(
                f"frame is {pixel_format} but the calibration was built for {self.pixel_format} frames"
            )
        try:
            h, w = frame_geometry(tuple(shape), pixel_format)
        except FrameMismatchError:
            h, w = -1, -1
        if (h, w) != (self.height, self.width) or np.dtype(dtype) != np.uint8:
            raise FrameMismatchError(
                f"frame is {np.dtype(dtype)} {tuple(shape)} but the calibration was built for "
                f"{self.width}x{self.height} uint8 {self.pixel_format} frames"
            )


class FiberSampler:
    """Per-frame fiber means from a :class:`FiberTable`, with preallocated buffers.

    Only the fiber pixels are read; for RGB frames only they are converted to
    gray (BT.601, or another colour mix, :mod:`optitac_edge.core.colour`), for
    YUV420 frames the Y plane is used as it is.
    """

    def __init__(self, table: FiberTable, colour_mix: str = "luma") -> None:
        self.table = table
        #: RGB frames: the Q15 weights of a mix other than luma (None: luma, OpenCV's conversion).
        self.mix: np.ndarray | None = (mix_weights(colour_mix) if table.pixel_format == "rgb"
                                       and colour_mix != "luma" else None)
        self._index = table.pixel_index.astype(np.intp)
        self._starts = table.pixel_start[:-1].astype(np.intp)
        self._inv_count = (1.0 / table.pixel_count).astype(np.float32)
        p = table.pixel_index.size
        rgb = table.pixel_format == "rgb"
        # RGB: one flat gather of the three bytes of every fiber pixel (faster than rows of 3),
        # then OpenCV's RGB -> gray on them as one row of pixels: the same rounded BT.601 gray
        # as cv2.cvtColor of the whole frame (fiber calibration, the reference method)
        # RGB: the three bytes of each fiber pixel (unused for gray and YUV420)
        self._index3 = (self._index[:, None] * 3 + np.arange(3)).ravel() if rgb else self._index
        self._rgb = np.empty((1, p, 3), dtype=np.uint8) if rgb else None
        # the fiber pixels' gray levels, uint8; summed in the narrowest unsigned integer that
        # holds 255 * the largest fiber's pixel count (exact; uint16 measures 3.7 us here against
        # 7.5 us for a float32 reduceat, which converts every pixel)
        most = int(table.pixel_count.max(initial=1))
        self._sums = np.zeros(table.n_fibers, dtype=np.uint16 if 255 * most <= 0xFFFF else np.uint32)
        # widened first (one cast copy, no temporary): reduceat with dtype= would cast through a new buffer
        self._wide = np.zeros(p, dtype=self._sums.dtype)
        self._sums32 = np.zeros(table.n_fibers, dtype=np.float32)  # the sums as float32 (no mixed-type product)
        self._gathered = np.empty(p, dtype=np.uint8)
        self._gathered_row = self._gathered.reshape(1, p)
        self._mix_work = np.empty(p if self.mix is not None else 0, dtype=np.int32)
        # one byte of every 64-byte block of the frame the gather reads, in address order
        flat = self._index3
        self._probe = (np.unique(flat // CACHE_LINE) * CACHE_LINE).astype(np.intp)
        self._probed = np.empty(self._probe.size, dtype=np.uint8)

    def kernel_arrays(self) -> dict[str, np.ndarray | int]:
        """What the compiled kernel reads (:mod:`optitac_edge.core.compiled`): the pixels of each fiber
        (int32, int64 starts), the reciprocal pixel counts and the frame's size."""
        t = self.table
        frame_bytes = t.height * t.width * (3 if t.pixel_format == "rgb" else 1)
        if t.pixel_format == "yuv420":
            frame_bytes = t.height * 3 // 2 * t.width
        out: dict[str, np.ndarray | int] = {
            "pixel_index": t.pixel_index.astype(np.int32), "pixel_start": t.pixel_start.astype(np.int64),
            "inv_count": self._inv_count, "rgb": int(t.pixel_format == "rgb"),
            "frame_pixels": t.height * t.width, "frame_bytes": frame_bytes}
        if self.mix is not None:
            out["rgb_weights"] = self.mix
        return out

    def means(self, frame: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Mean gray level of each fiber.

        Parameters
        ----------
        frame : ndarray, uint8
            A C-contiguous frame in the table's pixel format and size
            (checked by the caller with :meth:`FiberTable.check_frame`).
        out : ndarray, shape (N,), float32
            Receives the means, gray levels 0-255.
        """
        self.gather(frame)
        return self.reduce(out)

    def gather(self, frame: np.ndarray) -> np.ndarray:
        """The fiber pixels' gray levels (luma for RGB), in table order, into an internal buffer."""
        # A new frame is not in the CPU caches (the camera wrote it). The gather reads ~30
        # bytes of one cache line after another, so its misses come one at a time; reading
        # one byte of every block first, in address order, lets the CPU fetch them in
        # parallel (independent loads, the hardware prefetcher): 71 -> 47 us for an RGB
        # frame, 24 -> 17 us gray (640x480, 217 fibers, docs/performance.md). The blocks are
        # counted from the frame's start, not the memory's: a block that straddles two lines
        # touches one, which the adjacent-line prefetch mostly covers.
        # ndarray.take, not np.take (no Python wrapper); mode="wrap": the default "raise" copies
        # into a new buffer and then into ``out`` (a 21 kB allocation per frame), and the indices
        # are in range for every frame check_frame accepts (FiberTable checks them against its size)
        flat = frame.reshape(-1)
        flat.take(self._probe, out=self._probed, mode="wrap")
        if self._rgb is not None:
            flat.take(self._index3, out=self._rgb.reshape(-1), mode="wrap")
            if self.mix is None:
                cv2.cvtColor(self._rgb, cv2.COLOR_RGB2GRAY, dst=self._gathered_row)
            else:
                mix_pixels(self._rgb[0], self.mix, self._mix_work, self._gathered)
        else:
            flat.take(self._index, out=self._gathered, mode="wrap")
        return self._gathered

    def sums(self) -> np.ndarray:
        """Per-fiber sums of the gray levels of the last :meth:`gather`, exact, in an internal buffer:
        shape (N,), uint16 (uint32 for fibers of more than 257 pixels, :attr:`sum_dtype`)."""
        np.copyto(self._wide, self._gathered)
        np.add.reduceat(self._wide, self._starts, out=self._sums)
        return self._sums

    def channel_sums(self) -> np.ndarray:
        """Per-fiber sums of the red, green and blue levels of the last :meth:`gather` of an RGB frame, exact:
        shape (N, 3), :attr:`sum_dtype` (a new array; the recording writer's, not the frame loop's)."""
        if self._rgb is None:
            raise ValueError("channel sums need an RGB fiber table")
        return np.add.reduceat(self._rgb[0], self._starts, axis=0, dtype=np.int64).astype(self._sums.dtype)

    @property
    def sum_dtype(self) -> np.dtype:
        """The dtype of :meth:`sums`: the narrowest unsigned integer that holds every fiber's sum."""
        return self._sums.dtype

    def reduce(self, out: np.ndarray) -> np.ndarray:
        """Per-fiber means of the last :meth:`gather` into ``out`` (one segmented sum)."""
        np.copyto(self._sums32, self.sums())
        np.multiply(self._sums32, self._inv_count, out=out)
        return out
