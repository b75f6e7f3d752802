"""The live loop: the one place where frames come in and results go out.

Everything inside :class:`~optitac_edge.pipeline.Pipeline` is pure computation
on a frame and its timestamp; this module does the I/O around it.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from .bundle import CalibrationBundle
from .calibration import calibrate_fibers
from .cameras import Camera
from .contact import ContactEstimate
from .errors import CameraError

log = logging.getLogger(__name__)


@dataclass
class LoopStats:
    """Counters of a live run."""

    frames: int = 0
    contacts: int = 0
    started_ns: int = 0

    def fps(self, now_ns: int) -> float:
        elapsed = (now_ns - self.started_ns) / 1e9
        return self.frames / elapsed if elapsed > 0 else 0.0


def self_calibrate(camera: Camera, rest_frames: int = 10) -> CalibrationBundle:
    """Calibrate the fibers from the camera's first ``rest_frames`` frames (must be contact-free)."""
    frames = []
    while len(frames) < rest_frames:
        captured = camera.read()
        if captured is None:
            raise CameraError("camera ended before the rest frames were captured")
        frames.append(captured.frame.copy())
    return calibrate_fibers(frames, camera.pixel_format)


def run_loop(
    camera: Camera,
    bundle: CalibrationBundle,
    on_result: Callable[[ContactEstimate, LoopStats], None],
    stop: threading.Event,
    max_frames: int | None = None,
) -> LoopStats:
    """Process frames from ``camera`` until ``stop`` is set, the source ends or ``max_frames``.

    ``on_result`` is called with the (reused) estimate of every frame.
    """
    from .pipeline import Pipeline

    bundle.fibers.check_frame(_probe_frame(camera), camera.pixel_format)
    pipeline = Pipeline(bundle)
    stats = LoopStats(started_ns=time.monotonic_ns())
    while not stop.is_set() and (max_frames is None or stats.frames < max_frames):
        captured = camera.read()
        if captured is None:
            break
        estimate = pipeline.process(captured.frame, captured.t_ns)
        stats.frames += 1
        stats.contacts += int(estimate.contact)
        on_result(estimate, stats)
    log.info("live loop stopped after %d frames", stats.frames)
    return stats


def _probe_frame(camera: Camera):  # type: ignore[no-untyped-def]
    import numpy as np

    return np.zeros(camera.frame_shape, dtype=np.uint8)
