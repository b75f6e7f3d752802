"""In-process measurements: the whole frame and each stage, allocations, the reference against the fast pipeline."""

from __future__ import annotations

import time
import tracemalloc
from typing import Any

import numpy as np

from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.devtools.bench.samples import Samples, rss_bytes, summary, timed

STAGES = ("whole_frame", "gray", "fiber_means", "baseline", "surface", "segment", "moments", "hu",
          "shape", "calibration", "encode")


#: Frames (after the baseline) the pipeline runs before anything is measured; at least every
#: distinct frame once, so that the allocator's high-water mark for the largest contact (OpenCV's
#: temporaries, ~1.5 MB of heap once) is reached before RSS growth is counted.
WARMUP_FRAMES = 200


def _warmup(frames: list[np.ndarray], rest: int) -> int:
    return max(WARMUP_FRAMES, len(frames) - rest)


class StageTimer:
    """Times one pipeline's frames and re-runs each stage in isolation right after each frame,
    through the pipeline's parts' public methods."""

    def __init__(self, pipe: Pipeline, n: int) -> None:
        from optitac_edge.io.protocol.messages import ContactMessage
        from optitac_edge.io.protocol.wire import encode_contact

        self.pipe = pipe
        # preallocated, so that recording the samples does not grow the RSS being measured
        self.samples = {k: Samples(n) for k in STAGES}
        self._surface = np.zeros(pipe.surface.size, dtype=np.float32)
        self._msg = ContactMessage()
        self._scratch = ContactEstimate()
        self._encode = encode_contact
        c = pipe.corrector
        self._shapes = c.shapes if c is not None else None
        self._centroid = c.centroid if c is not None else None
        self._width = c.width if c is not None else None

    def frame(self, frame: np.ndarray, t_ns: int) -> ContactEstimate:
        p = self.pipe
        s = self.samples
        t0 = time.perf_counter_ns()
        result = p.process_recorded(frame, t_ns)
        est = result.primary
        s["whole_frame"].append(time.perf_counter_ns() - t0)
        if not result.baseline_ready:
            return est
        s["gray"].append(timed(p.parts.sampler.gather, frame))
        s["fiber_means"].append(timed(p.parts.sampler.reduce, p.means))
        s["baseline"].append(timed(p.parts.compute_signal, p.means, t_ns))
        s["surface"].append(timed(p.parts.surface_op.compute, p.signal, self._surface))
        s["segment"].append(timed(self._segment))
        if est.contact:
            box = p.parts.segmenter.box(p.surface)  # the pipeline's truncated surface (not timed)
            s["moments"].append(timed(p.parts.blobs.ellipse, box.img, box.x, box.y, self._scratch))
            s["hu"].append(timed(self._hu, box.img, box.peak))
            if self._shapes is not None:
                s["shape"].append(timed(self._shapes.classify, est.features))
            if self._centroid is not None or self._width is not None:
                s["calibration"].append(timed(self._lookup, est))
        s["encode"].append(timed(self._encode_frame, est, t_ns))
        return est

    def _segment(self) -> None:
        """Truncation, the bounding box and (several contacts allowed) the partition."""
        p = self.pipe
        seg = p.parts.segmenter
        cells = seg.truncate(self._surface)
        if cells:
            box = seg.box(self._surface)
            if p.options.max_contacts > 1:
                seg.partition(box, cells)

    def _hu(self, img: np.ndarray, peak: float) -> None:
        blobs = self.pipe.parts.blobs
        blobs.shape_features(img, blobs.levels_of(peak)[1], self._scratch)

    def _lookup(self, est: ContactEstimate) -> None:
        if self._centroid is not None:
            self._centroid.correct(est.x_mm, est.y_mm)
        if self._width is not None:
            self._width.correct(est.major_mm, est.minor_mm, est.x_mm, est.y_mm)

    def _encode_frame(self, est: ContactEstimate, t_ns: int) -> None:
        self._msg.fill(est, t_ns, t_ns, True)
        self._encode(self._msg, 0)


def _feed(pipe: Any, frames: list[np.ndarray], rest: int, n: int, t_ns: int, period_ns: int,
          on_frame: Any = None) -> int:
    """Process ``n`` frames cycling over ``frames[rest:]`` (after the rest frames); returns the clock."""
    k = len(frames) - rest
    for i in range(n):
        frame = frames[rest + i % k]
        if on_frame is None:
            pipe.process_recorded(frame, t_ns)
        else:
            on_frame(frame, t_ns)
        t_ns += period_ns
    return t_ns


def measure_stages(bundle: Any, frames: list[np.ndarray], rest: int, n: int, fps: float) -> dict[str, Any]:
    """Whole-frame and per-stage times over ``n`` frames, RSS growth over them, contact share."""
    period = int(1e9 / fps)
    pipe = Pipeline(bundle)
    t = _feed(pipe, frames[:rest], 0, rest, 0, period) if rest else 0
    # warm-up with the stage re-runs too (their OpenCV temporaries reach their high-water mark)
    warm = _warmup(frames, rest)
    t = _feed(pipe, frames, rest, warm, t, period, StageTimer(pipe, warm).frame)
    timer = StageTimer(pipe, n)
    contacts = [0]

    def one(frame: np.ndarray, t_ns: int) -> None:
        contacts[0] += timer.frame(frame, t_ns).contact

    rss0 = rss_bytes()
    _feed(pipe, frames, rest, n, t, period, one)
    rss1 = rss_bytes()
    return {"frames": n, "contact_fraction": round(contacts[0] / max(n, 1), 3),
            "stages": {k: summary(v.values) for k, v in timer.samples.items()},
            "rss_growth_bytes": rss1 - rss0, "rss_bytes": rss1,
            "surface": type(pipe.parts.surface_op).__name__}


def measure_memory(bundle: Any, frames: list[np.ndarray], rest: int, n: int, fps: float) -> dict[str, Any]:
    """tracemalloc: net bytes per frame after warm-up, and the largest transient within a frame."""
    period = int(1e9 / fps)
    pipe = Pipeline(bundle)
    t = _feed(pipe, frames[:rest], 0, rest, 0, period) if rest else 0
    t = _feed(pipe, frames, rest, _warmup(frames, rest), t, period)
    tracemalloc.start()
    try:
        t = _feed(pipe, frames, rest, 50, t, period)  # tracemalloc's own first allocations
        transient = [0]

        def one(frame: np.ndarray, t_ns: int) -> None:
            tracemalloc.reset_peak()
            before = tracemalloc.get_traced_memory()[0]
            pipe.process_recorded(frame, t_ns)
            transient[0] = max(transient[0], tracemalloc.get_traced_memory()[1] - before)

        before = tracemalloc.get_traced_memory()[0]
        _feed(pipe, frames, rest, n, t, period, one)
        after = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    return {"frames": n, "net_bytes_per_frame": (after - before) / max(n, 1),
            "net_bytes_total": after - before, "max_transient_bytes_in_frame": transient[0]}
