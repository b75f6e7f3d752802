"""Replay a recording as a camera, at its recorded frame rate or as fast as possible."""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from optitac_edge.io.cameras.base import Camera, CapturedFrame
from optitac_edge.io.recording import Recording

if TYPE_CHECKING:
    from optitac_edge.io.cameras.section import CameraConfig
    from optitac_edge.io.device import BoardView


class RecordingCamera(Camera):
    """Frames of a recording directory, streamed from its memory map.

    Parameters
    ----------
    path : path-like
        Recording directory.
    realtime : bool
        Pace frames at the recording's ``fps`` (True) or deliver them as fast
        as they are read (False).
    loop : bool
        Start again after the last frame instead of ending.

    Each frame carries its recorded capture time (``Recording.t_ns``), moved to
    the moment the camera was opened: replayed as fast as read, a recording
    still has its own timing.
    """

    @classmethod
    def section_kwargs(cls, section: CameraConfig, board: BoardView) -> dict[str, Any]:
        """``[camera] recording``, played at its own rate."""
        return {"path": section.recording, "realtime": True}

    def __init__(self, path: str | Path, realtime: bool = False, loop: bool = False) -> None:
        super().__init__()
        self.recording = Recording(path)
        self.pixel_format = self.recording.pixel_format
        self.height, self.width = self.recording.height, self.recording.width
        self.fps = self.recording.meta.fps
        self._realtime = realtime
        self._loop = loop
        self._index = 0
        self._seq = 0
        self._next_ns = time.monotonic_ns()
        # frames are stamped with their recorded capture times (timestamps.npy, else i / fps),
        # moved to start now; a loop continues one frame period after the last frame
        t = self.recording.t_ns
        self._times = t - t[0]
        self._period_ns = int(1e9 / self.fps)
        self._t0_ns = time.monotonic_ns()

    def _read_internal(self, timeout_s: float) -> CapturedFrame | None:
        if self._index >= len(self.recording):
            if not self._loop:
                return None
            self._t0_ns += int(self._times[-1]) + self._period_ns
            self._index = 0
        if self._realtime:
            delay = (self._next_ns - time.monotonic_ns()) / 1e9
            if delay > 0:
                time.sleep(delay)
            self._next_ns = max(self._next_ns, time.monotonic_ns() - 1_000_000_000) + int(1e9 / self.fps)
        frame = self.recording.frame(self._index)
        t_ns = self._t0_ns + int(self._times[self._index])
        self._index += 1
        self._seq += 1
        return CapturedFrame(frame, t_ns, self._seq)

    def _close_internal(self) -> None:
        self.recording = None  # type: ignore[assignment]  # drop the memory map
