"""Is a camera frame worth processing? A cheap check before the pipeline: wrong, dark, saturated.

One pixel (the centre) of every live fiber is sampled (the luminance plane;
all three bytes for RGB): a frame with most of them at full scale is
skipped as saturated, one with fewer than :data:`DARK_FRACTION` of them above
:data:`DARK_LEVEL` as dark; a frame of the wrong shape or dtype is bad. A
frame that passes but has some fiber centre at full scale is processed with
:attr:`FrameCheck.saturated` set (the SATURATED flag on the wire).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from optitac_edge.core.fiber_table import FiberTable

#: Fewer than DARK_FRACTION of the sampled fiber centres above this gray level: the frame is dark.
DARK_LEVEL = 8
DARK_FRACTION = 0.1
#: Gray level counted as saturated (full scale).
SATURATED_LEVEL = 255
#: More than this fraction of the live fibers' centres saturated: the frame is skipped.
SATURATED_FRACTION = 0.5


def probe_offsets(table: FiberTable) -> tuple[np.ndarray, int]:
    """The bytes the check reads: one pixel (the centre) of every live fiber (of every fiber when all are
    dead), as flat byte offsets into a frame (RGB: the pixel's three bytes, in turn); and the pixels' count.

    Returns
    -------
    probe : ndarray, shape (P,) or (3 P,), intp
    n_probes : int
        P.
    """
    col = np.clip(np.rint(table.centroid_px[:, 0]), 0, table.width - 1).astype(np.intp)
    row = np.clip(np.rint(table.centroid_px[:, 1]), 0, table.height - 1).astype(np.intp)
    live = ~table.dead if (~table.dead).any() else np.ones_like(table.dead)
    probe = (row * table.width + col)[live]
    if table.pixel_format == "rgb":  # the three bytes of each probed pixel
        probe = (probe[:, None] * 3 + np.arange(3)).ravel()
    return probe, int(live.sum())


def check_kernel_arrays(table: FiberTable) -> dict[str, np.ndarray | int | float]:
    """What the compiled kernel reads to check a frame as :class:`FrameCheck` does (after the fiber means,
    from the same pixels in its caches): the probe offsets (int32) and the levels."""
    probe, n_probes = probe_offsets(table)
    return {"check_probe": probe.astype(np.int32), "check_pixels": n_probes,
            "check_bytes": 3 if table.pixel_format == "rgb" else 1, "check_dark_level": float(DARK_LEVEL),
            "check_dark_fraction": float(DARK_FRACTION), "check_saturated_level": float(SATURATED_LEVEL),
            "check_saturated_fraction": float(SATURATED_FRACTION)}


#: The reasons :meth:`FrameCheck.__call__` gives, by the compiled kernel's check codes 1 and 2.
CHECK_REASONS = ("dark", "saturated")


class FrameCheck:
    """The check of one bundle's frames; allocates nothing per call.

    Parameters
    ----------
    table : FiberTable
        The bundle's fiber table (frame size, pixel format, fiber centres, dead fibers).
    frame_shape : tuple of int
        The array shape the camera delivers.
    """

    def __init__(self, table: FiberTable, frame_shape: tuple[int, ...]) -> None:
        self._rgb = table.pixel_format == "rgb"
        self._probe, self._n_probes = probe_offsets(table)
        self._values = np.zeros(self._probe.size, dtype=np.uint8)
        self._flags = np.zeros(self._probe.size, dtype=bool)
        self.frame_shape = tuple(frame_shape)
        #: The last frame that passed had a live fiber centre at full scale.
        self.saturated = False

    def bad(self, frame: object) -> bool:
        """Whether ``frame`` is no frame of this camera: not a uint8 array of :attr:`frame_shape` (the part of
        the check that reads no pixel; calling the check does the rest)."""
        return not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.shape != self.frame_shape

    def _count(self, flags: np.ndarray) -> int:
        """Probed pixels flagged (for RGB: any of a pixel's three bytes)."""
        return int(np.count_nonzero(flags.reshape(-1, 3).any(axis=1))) if self._rgb else int(np.count_nonzero(flags))

    def __call__(self, frame: Any) -> str | None:  # untrusted: any object (bad() says so first)
        """Why ``frame`` must be skipped (``"bad"``, ``"dark"``, ``"saturated"``), or None.

        Also sets :attr:`saturated` when some live fiber centre is at full scale.
        Costs one gather of a pixel per fiber into a preallocated buffer and its minimum and
        maximum; two counts only when some probe is dark or at full scale.
        """
        self.saturated = False
        if self.bad(frame):
            return "bad"
        values, flags = self._values, self._flags
        frame.reshape(-1).take(self._probe, out=values, mode="wrap")  # in range for a frame of this shape
        low, high = cv2.minMaxLoc(values)[:2]
        if low > DARK_LEVEL and high < SATURATED_LEVEL:  # the usual frame: one gather and one pass
            return None
        np.greater_equal(values, SATURATED_LEVEL, out=flags)
        n_sat = self._count(flags)
        if n_sat > SATURATED_FRACTION * self._n_probes:
            return "saturated"
        np.greater(values, DARK_LEVEL, out=flags)
        if self._count(flags) < DARK_FRACTION * self._n_probes:
            return "dark"
        self.saturated = n_sat > 0
        return None
