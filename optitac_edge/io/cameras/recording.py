"""Replay a recording as a camera, at its recorded frame rate or as fast as possible."""

from __future__ import annotations

import threading
import time
from collections import deque
from pathlib import Path
from typing import TYPE_CHECKING, Any

from optitac_edge.errors import CameraError
from optitac_edge.io.cameras.base import Camera, CapturedFrame
from optitac_edge.io.cameras.frame_ring import check_queue_frames
from optitac_edge.io.recording import Recording
from optitac_edge.io.threads import NamedThread

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
    live : bool
        With ``realtime``: deliver the frames as a camera that writes frames by DMA does, from a capture
        thread that queues each frame at its time (up to ``queue_frames``; a frame the loop does not take in
        time is dropped and counted, none is waited for). The frames are the recording's memory map, not
        copies: the loop reads bytes no core wrote recently, as from a DMA buffer, and its own thread does
        not sleep or read ahead for the camera.
    queue_frames : int
        ``live``: frames that may wait for the loop.

    Each frame carries its recorded capture time (``Recording.t_ns``), moved to
    the moment the camera was opened: replayed as fast as read, a recording
    still has its own timing.
    """

    @classmethod
    def section_kwargs(cls, section: CameraConfig, board: BoardView) -> dict[str, Any]:
        """``[camera] recording``, played at its own rate."""
        return {"path": section.recording, "realtime": True, "queue_frames": section.queue_frames}

    def __init__(self, path: str | Path, realtime: bool = False, loop: bool = False, live: bool = False,
                 queue_frames: int = 4) -> None:
        super().__init__()
        if live and not realtime:
            raise CameraError("recording camera: live needs realtime (frames at the recording's rate)")
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
        self._live = live
        self._depth = check_queue_frames(queue_frames)
        self._waiting: deque[CapturedFrame] = deque()
        self._due = threading.Condition()
        self._finished = False
        self._error: str | None = None
        #: ``live``: frames dropped because ``queue_frames`` newer ones were waiting.
        self.overwritten = 0
        self._stop = threading.Event()
        if live:
            self._thread = NamedThread(target=self._capture_loop, name="optitac-replay", daemon=True)
            self._thread.start()

    def _read_internal(self, timeout_s: float) -> CapturedFrame | None:
        if self._live:
            return self._take_live(timeout_s)
        return self._next()

    def _next(self) -> CapturedFrame | None:
        """The next frame at its time (sleeping until then with ``realtime``); None at the end."""
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

    def _capture_loop(self) -> None:
        try:
            while not self._stop.is_set():
                captured = self._next()
                with self._due:
                    if captured is None:
                        self._finished = True
                    elif len(self._waiting) == self._depth:
                        self._waiting.popleft()
                        self.overwritten += 1
                    if captured is not None:
                        self._waiting.append(captured)
                    self._due.notify_all()
                if captured is None:
                    return
        except Exception as exc:  # noqa: BLE001 - reported to the reader, never a silent end
            with self._due:
                self._error = f"recording camera: replay failed: {exc}"
                self._due.notify_all()

    def _take_live(self, timeout_s: float) -> CapturedFrame | None:
        deadline = time.monotonic() + timeout_s
        with self._due:
            while not self._waiting:
                if self._error is not None:
                    raise CameraError(self._error)
                if self._finished:
                    return None
                left = deadline - time.monotonic()
                if left <= 0:
                    raise CameraError(f"no frame from the recording within {timeout_s:.3g} s")
                self._due.wait(left)
            return self._waiting.popleft()

    def _close_internal(self) -> None:
        self._stop.set()
        if self._live:
            self._thread.join(timeout=2.0)
        self.recording = None  # type: ignore[assignment]  # drop the memory map
