"""A finite camera of given frames, for service tests."""

from __future__ import annotations

import numpy as np

from optitac_edge.io.cameras.base import Camera, CapturedFrame


class ListCamera(Camera):
    """A finite camera: the given frames, one every 1/240 s of the frame clock."""

    def __init__(self, frames: list[np.ndarray]) -> None:
        super().__init__()
        self.frames, self.k = frames, 0
        self.height, self.width = frames[0].shape[:2]
        self.pixel_format, self.fps = "gray", 240.0

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return self.frames[0].shape

    def _read_internal(self, timeout_s: float) -> CapturedFrame | None:
        if self.k >= len(self.frames):
            return None
        self.k += 1
        return CapturedFrame(self.frames[self.k - 1], self.k * 4_166_667, self.k)

    def _close_internal(self) -> None:
        pass
