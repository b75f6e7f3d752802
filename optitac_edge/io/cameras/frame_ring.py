"""Frames handed from a capture thread to the frame loop: a short queue, oldest dropped.

A capture thread writes each frame into :attr:`FrameRing.back` and calls
:meth:`FrameRing.publish`; the frame loop calls :meth:`FrameRing.take`. Up to
``depth`` frames wait; when one more comes, the oldest waiting frame is
dropped (counted in :attr:`FrameRing.overwritten`, and a gap in ``seq`` for the
reader). ``depth = 1`` is a latest-frame slot. A deeper ring rides out a
pause of the loop (a scheduler hiccup) of up to ``depth`` frame periods: the
frames are processed late instead of lost.

All buffers are allocated once: ``depth`` waiting, one being written by the
capture thread and one held by the reader (valid until its next ``take``).
"""

from __future__ import annotations

import threading
import time
from collections import deque

import numpy as np

from optitac_edge.errors import CameraError
from optitac_edge.io.cameras import MAX_QUEUE_FRAMES

#: Most frames a ring may hold waiting (``camera.queue_frames``'s upper bound).
MAX_DEPTH = MAX_QUEUE_FRAMES


def check_queue_frames(depth: object) -> int:
    """``depth`` if it is a valid ``queue_frames`` (an integer 1..``MAX_DEPTH``), else CameraError."""
    if not isinstance(depth, int) or isinstance(depth, bool) or not 1 <= depth <= MAX_DEPTH:
        raise CameraError(f"queue_frames must be an integer 1..{MAX_DEPTH}, not {depth!r}")
    return depth


class FrameRing:
    """A bounded queue of preallocated frame buffers between one writer and one reader.

    Parameters
    ----------
    shape : tuple of int
        Shape of every frame (uint8).
    depth : int
        Frames that may wait for the reader, 1..``MAX_DEPTH``.
    """

    def __init__(self, shape: tuple[int, ...], depth: int) -> None:
        self.depth = check_queue_frames(depth)
        self._bufs = [np.empty(shape, np.uint8) for _ in range(depth + 2)]
        self._views = []
        for b in self._bufs:
            v = b.view()
            v.flags.writeable = False
            self._views.append(v)
        self._back = 0
        self._free = list(range(1, depth + 2))
        self._waiting: deque[tuple[int, int, int]] = deque()  # (buffer, t_ns, seq), oldest first
        self._front: int | None = None  # the buffer the reader holds
        self._cond = threading.Condition()
        self._error: str | None = None
        self._published = 0
        #: Frames dropped because ``depth`` newer ones were waiting.
        self.overwritten = 0

    @property
    def back(self) -> np.ndarray:
        """The buffer the capture thread writes the next frame into (writable)."""
        return self._bufs[self._back]

    @property
    def published(self) -> int:
        """Frames published so far."""
        return self._published

    def publish(self, t_ns: int, seq: int) -> None:
        """Queue the frame just written into :attr:`back`; a fresh ``back`` follows."""
        with self._cond:
            if len(self._waiting) == self.depth:
                self._free.append(self._waiting.popleft()[0])
                self.overwritten += 1
            self._waiting.append((self._back, t_ns, seq))
            self._back = self._free.pop()
            self._published += 1
            self._cond.notify_all()

    def fail(self, message: str) -> None:
        """The source failed: :meth:`take` raises ``CameraError(message)`` once the queue is empty."""
        with self._cond:
            self._error = message
            self._cond.notify_all()

    def wait_first(self, timeout_s: float) -> bool:
        """Wait until a frame was published or the source failed; False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: self._published > 0 or self._error is not None,
                                       timeout=timeout_s)

    @property
    def error(self) -> str | None:
        """The failure reported by the capture thread, if any."""
        return self._error

    def take(self, timeout_s: float, source: str) -> tuple[np.ndarray, int, int]:
        """The oldest waiting frame as ``(read-only frame, t_ns, seq)``.

        The frame stays valid until the next ``take``.

        Raises
        ------
        CameraError
            The source failed (and nothing is waiting), or no frame came within ``timeout_s``.
        """
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self._waiting:
                if self._error is not None:
                    raise CameraError(self._error)
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise CameraError(f"no frame from {source} within {timeout_s:.3g} s")
                self._cond.wait(remaining)
            if self._front is not None:
                self._free.append(self._front)
            self._front, t_ns, seq = self._waiting.popleft()
        return self._views[self._front], t_ns, seq
