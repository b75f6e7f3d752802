"""A camera that publishes pre-rendered frames at the camera's rate from a capture thread, and why frames dropped."""

from __future__ import annotations

import os
import threading
import time
from collections import deque
from typing import Any

import numpy as np

from optitac_edge.errors import CameraError
from optitac_edge.io.cameras.base import Camera, CapturedFrame
from optitac_edge.io.threads import NamedThread


def dropped_in_stall(now_ns: int, due_ns: int, dropped_published_ns: int, period_ns: float) -> bool:
    """Whether a frame pushed out of the replay camera's queue at ``now_ns`` was lost to a process stall.

    Yes when the frame pushing it out is published a period or more after it was due
    (nothing in the process ran, the capture thread included), or when the dropped
    frame itself had waited less than half a period: it came in the burst of late
    frames the capture thread publishes right after such a stall, and the loop, back
    from the same stall, had no time to take it. Otherwise the capture thread was on
    time and the frame waited its ``queue_frames`` periods: the loop's own drop.
    """
    return now_ns - due_ns >= period_ns or now_ns - dropped_published_ns < period_ns / 2


class PacedReplayCamera(Camera):
    """Frames (rest first, then the rest cycled) published at ``k / fps`` by a capture thread.

    The thread starts at the loop's first read, so the rest frames reach the
    baseline however long the service takes to be built (a run whose first
    frames were lost would take its baseline over presses and measure another
    workload). It queues each frame, stamped when published, as the hardware
    backends' frame ring does: up to ``queue_frames`` wait, and when one more
    comes the oldest is dropped (a gap in ``seq``, counted as dropped). Like a
    camera whose driver delivers by DMA: the source costs the loop nothing, so
    the loop itself is measured.
    """

    def __init__(self, frames: list[np.ndarray], rest: int, fps: float, pixel_format: str,
                 queue_frames: int) -> None:
        super().__init__()
        h, w = frames[0].shape[:2]
        self.pixel_format, self.fps = pixel_format, fps
        self.height, self.width = (h * 2 // 3, w) if pixel_format == "yuv420" else (h, w)
        self._frames, self._rest, self._queue_frames = frames, rest, queue_frames
        self._waiting: deque[CapturedFrame] = deque()
        #: (seq, stalled) of each frame dropped from the queue (the loop had not taken it when
        #: ``queue_frames`` newer ones came), see :func:`dropped_in_stall`
        self.overwritten: list[tuple[int, bool]] = []
        #: (seq, ns late) of each frame the capture thread published a period or more late
        self.stalls: list[tuple[int, int]] = []
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._thread = NamedThread(target=self._capture, name="bench-capture", daemon=True)

    def _capture(self) -> None:
        frames, rest = self._frames, self._rest
        period = 1e9 / self.fps
        t0 = time.monotonic_ns()
        k, seq = len(frames) - rest, 0
        while not self._stop.is_set():
            due = t0 + int(seq * period)
            now = time.monotonic_ns()
            if due > now:
                time.sleep((due - now) / 1e9)
            i = seq if seq < len(frames) else rest + (seq - rest) % k
            with self._cond:
                now = time.monotonic_ns()
                if now - due >= period:
                    self.stalls.append((seq + 1, now - due))
                if len(self._waiting) == self._queue_frames:
                    old = self._waiting.popleft()
                    self.overwritten.append((old.seq, dropped_in_stall(now, due, old.t_ns, period)))
                self._waiting.append(CapturedFrame(frames[i], now, seq + 1))
                self._cond.notify_all()
            seq += 1

    def _read_internal(self, timeout_s: float) -> CapturedFrame:
        deadline = time.monotonic() + timeout_s
        with self._cond:
            if self._thread.ident is None and not self._stop.is_set():
                self._thread.start()
            while not self._waiting:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise CameraError("replay camera: no frame in time")
                self._cond.wait(left)
            return self._waiting.popleft()

    def _close_internal(self) -> None:
        with self._cond:
            self._stop.set()
        if self._thread.ident is not None:
            self._thread.join(timeout=1.0)


def paced_replay_camera(frames: list[np.ndarray], rest: int, fps: float, pixel_format: str,
                        queue_frames: int) -> PacedReplayCamera:
    """A camera delivering pre-rendered frames at ``fps`` from a capture thread (see :class:`PacedReplayCamera`)."""
    return PacedReplayCamera(frames, rest, fps, pixel_format, queue_frames)


def steal_jiffies() -> int:
    """CPU time the hypervisor gave to others while this VM wanted it (/proc/stat), jiffies."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) if fields[0] == "cpu" and len(fields) > 8 else 0
    except (OSError, ValueError):
        return 0


def drop_causes(camera: Any, fps: float, steal_jiffies: int) -> dict[str, Any]:
    """Why frames were dropped: the loop too slow with the camera on time, or whole-process stalls.

    Only frames between the first and the last one the loop read count: the capture
    thread publishes from its start (while the service is still being built) until
    the camera is closed after the run.
    """
    if not hasattr(camera, "overwritten") or camera._last_seq is None:  # live sim camera: not classified
        return {}
    last = camera._last_seq
    first = last - (camera.frames_read + camera.frames_dropped) + 1
    lost = [stalled for seq, stalled in list(camera.overwritten) if first < seq < last]
    stalls = np.asarray([ns for seq, ns in list(camera.stalls) if first < seq <= last], dtype=np.float64) / 1e6
    return {"frames_dropped_by_pipeline": lost.count(False),
            "frames_dropped_in_process_stalls": lost.count(True),
            "process_stalls": {"count": int(stalls.size),
                               "max_ms": round(float(stalls.max()), 2) if stalls.size else 0.0,
                               "threshold_ms": round(1e3 / fps, 2)},
            "cpu_steal_ms": steal_jiffies * 1000 // os.sysconf("SC_CLK_TCK")}
