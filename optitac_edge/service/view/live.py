"""The live view's model: what the frame loop hands over, and the worker that turns it into a picture and data.

The frame loop calls :meth:`LiveView.observe` after every frame. At most
``rate_hz`` times a second it copies the frame and the pipeline's state into
preallocated buffers under a lock it only *tries* to take (never waits): if
the worker is swapping buffers at that instant, the update is skipped and
counted. The worker thread does everything else off the frame thread --
gray conversion, JPEG encoding, JSON -- and publishes the result by
replacing one reference. Actions from the page (tare, a new bundle) are
queued (bounded) and applied by the frame loop between frames.
"""

from __future__ import annotations

import base64
import json
import logging
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.frames import to_gray
from optitac_edge.core.pipeline import MAX_CONTACTS
from optitac_edge.errors import OptiTacError
from optitac_edge.io.threads import NamedThread
from optitac_edge.service.view.render import DARK_FRACTION, SATURATED_LEVEL, Published

if TYPE_CHECKING:
    from optitac_edge.calibration.edge_presses import EdgePresses
    from optitac_edge.calibration.orientation import OrientationFit
    from optitac_edge.core.image_transform import ImageTransform
    from optitac_edge.core.pipeline import Pipeline
    from optitac_edge.service.stats import ServiceStats

log = logging.getLogger(__name__)

#: Contact fields copied per contact (columns of the contact buffer).
CONTACT_FIELDS = ("x_mm", "y_mm", "major_mm", "minor_mm", "angle_deg", "strength", "confidence", "area_mm2",
                  "vx_mm_s", "vy_mm_s", "sliding")
#: A moving contact's arrow: where it will be this long from now, s (at most ARROW_MAX_MM long).
ARROW_S = 0.25
ARROW_MAX_MM = 8.0
#: Contacts slower than this (and not sliding) get no arrow, mm/s.
ARROW_MIN_MM_S = 2.0
#: Service counters shown (from ServiceStats).
STAT_FIELDS = ("frames", "contacts", "frames_dropped", "camera_errors", "light_changes", "processing_errors")
#: JPEG quality of the camera picture.
JPEG_QUALITY = 80


def contact_arrow(transform: ImageTransform, values: dict[str, float], sliding: bool) -> list[list[float]] | None:
    """A moving contact's arrow in image pixels (``transform``: the bundle's): from its centroid to where it
    will be in ARROW_S (at most ARROW_MAX_MM away); None for a contact held still or without a velocity."""
    vx, vy = values["vx_mm_s"], values["vy_mm_s"]
    speed = math.hypot(vx, vy) if math.isfinite(vx) and math.isfinite(vy) else 0.0
    if not (sliding or speed >= ARROW_MIN_MM_S) or speed == 0.0:
        return None
    length = min(speed * ARROW_S, ARROW_MAX_MM) / speed
    x, y = values["x_mm"], values["y_mm"]
    uv = transform.layout_to_image(np.array([[x, y], [x + vx * length, y + vy * length]]))
    return np.round(uv, 1).tolist()


def lower_priority(niceness: int = 10) -> None:
    """Run the calling thread at a lower scheduling priority (Linux: per-thread nice), best effort.

    The view's threads then take the CPU only when the frame loop does not need it.
    """
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), niceness)
    except (AttributeError, OSError):
        pass


class _Buffers:
    """One copy of everything an update needs (two of them: the loop fills one, the worker reads the other)."""

    def __init__(self, frame_shape: tuple[int, ...], n_fibers: int, n_cells: int) -> None:
        self.frame = np.empty(frame_shape, dtype=np.uint8)
        self.means = np.zeros(n_fibers, dtype=np.float32)
        self.surface = np.zeros(n_cells, dtype=np.float32)
        self.contacts = np.full((MAX_CONTACTS, len(CONTACT_FIELDS)), np.nan)
        self.shapes: list[str] = [""] * MAX_CONTACTS
        self.n_contacts = 0
        self.stats = np.zeros(len(STAT_FIELDS), dtype=np.int64)
        self.t_ns = 0
        self.fps = 0.0
        self.trunc = 0.0
        self.baseline_ready = False
        self.link = ""
        self.vibration = math.nan
        self.vibrating = False
        self.full = False


class LiveView:
    """Live data for the view server, fed by the frame loop, computed by a worker thread.

    Parameters
    ----------
    bundle : CalibrationBundle
        The fiber map drawn over the frames.
    pixel_format : str
    rate_hz : float
        Most updates a second.
    link : callable, optional
        Returns a short description of the link to the MCU (called by the worker).
    """

    def __init__(self, bundle: CalibrationBundle, pixel_format: str, rate_hz: float = 20.0,
                 link: Callable[[], str] | None = None) -> None:
        self.bundle = bundle
        self.pixel_format = pixel_format
        self.period_ns = int(1e9 / rate_hz)
        self.link = link or (lambda: "none")
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._published = threading.Condition()
        self._fill: _Buffers | None = None
        self._spare: _Buffers | None = None
        self._next_ns = 0
        self._seq = 0
        self._last: tuple[int, int] | None = None
        #: Updates skipped because the worker was swapping buffers (the loop never waits).
        self.skipped = 0
        self.published: Published | None = None
        self.actions: deque[tuple[str, Pipeline | None]] = deque(maxlen=16)  # ("tare", None), ("swap", new)
        self.message = ""
        self.procedure: EdgePresses | None = None  # while the guided orientation runs
        #: Where an oriented bundle is written (None: kept in memory).
        self.bundle_path: Path | None = None
        #: Called by the frame loop with a new pipeline (the service sets it).
        self.swap_pipeline: Callable[[Pipeline], None] | None = None
        #: Told every prompt of the guided orientation ("" when it ends), e.g. a simulated operator's.
        self.on_prompt: Callable[[str], None] | None = None
        self._thread = NamedThread(target=self._work, name="optitac-view", daemon=True)
        self._thread.start()

    # -- the frame loop's side ----------------------------------------------------------------

    def observe(self, frame: np.ndarray, t_ns: int, pipeline: Pipeline, stats: ServiceStats) -> None:
        """Hand over this frame if an update is due; apply one queued action. Never blocks."""
        if self.actions:
            self._apply(pipeline)
        if t_ns < self._next_ns or not self._lock.acquire(blocking=False):
            return
        try:
            b = self._fill
            if b is None or b.frame.shape != frame.shape:
                n = pipeline.surface.size
                b = self._fill = _Buffers(frame.shape, pipeline.means.size, n)
                self._spare = _Buffers(frame.shape, pipeline.means.size, n)
            np.copyto(b.frame, frame)
            np.copyto(b.means, pipeline.means)
            np.copyto(b.surface, pipeline.surface.reshape(-1))
            result = pipeline.result
            b.n_contacts = result.n_contacts
            for k, c in enumerate(result.touching()):
                for j, name in enumerate(CONTACT_FIELDS):
                    b.contacts[k, j] = getattr(c, name)
                b.shapes[k] = c.shape
            for j, name in enumerate(STAT_FIELDS):
                b.stats[j] = getattr(stats, name)
            b.t_ns, b.trunc = t_ns, float(pipeline.levels.trunc)
            b.vibration, b.vibrating = float(result.vibration), bool(result.vibrating)
            b.baseline_ready = bool(pipeline.baseline_ready)
            b.full = True
        finally:
            self._lock.release()
        self._next_ns = t_ns + self.period_ns
        self._wake.set()

    def _apply(self, pipeline: Pipeline) -> None:
        kind, value = self.actions.popleft()
        if kind == "tare":
            pipeline.reset_baseline()
            self.message = "tare: the baseline is taken again"
        elif kind == "swap" and self.swap_pipeline is not None and value is not None:
            self.swap_pipeline(value)

    # -- the worker -----------------------------------------------------------------------------

    def _take(self) -> _Buffers | None:
        with self._lock:  # the swap: microseconds
            b = self._fill
            if b is None or not b.full:
                return None
            self._fill, self._spare = self._spare, b
            return b

    def _work(self) -> None:
        lower_priority()
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            b = self._take()
            if b is None:
                continue
            try:
                self._publish(b)
            except Exception:
                log.exception("live view update failed")
            finally:
                b.full = False

    def _publish(self, b: _Buffers) -> None:
        frames = int(b.stats[0])
        if self._last is not None and b.t_ns > self._last[0]:
            b.fps = (frames - self._last[1]) * 1e9 / (b.t_ns - self._last[0])
        self._last = (b.t_ns, frames)
        gray = to_gray(b.frame, self.pixel_format)
        ok, jpeg = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        n = self.bundle.grid.n
        surface = b.surface.reshape(n, n).copy()
        contacts = [self._contact(b, k) for k in range(b.n_contacts)]
        procedure = self.procedure
        if procedure is not None and b.baseline_ready:
            c = contacts[0] if contacts else None
            before = procedure.prompt
            procedure.feed(c is not None, c["x_mm"] if c else math.nan, c["y_mm"] if c else math.nan, b.t_ns)
            if procedure.done:
                self.message = self._oriented(procedure.fit)
                self.procedure = None
            if procedure.prompt != before:
                self._tell(procedure.prompt)
        self._seq += 1
        state = self._state(b, surface, contacts)
        published = Published(self._seq, json.dumps(state, separators=(",", ":")).encode(),
                              jpeg.tobytes() if ok else b"", surface, gray, contacts, b.means.copy())
        with self._published:
            self.published = published
            self._published.notify_all()

    def _contact(self, b: _Buffers, k: int) -> dict[str, Any]:
        values = dict(zip(CONTACT_FIELDS, (float(v) for v in b.contacts[k])))
        t = self.bundle.transform
        a = math.radians(values["angle_deg"]) if math.isfinite(values["angle_deg"]) else 0.0
        phi = np.linspace(0, 2 * math.pi, 33)
        ma = values["major_mm"] / 2 if math.isfinite(values["major_mm"]) else 1.0
        mi = values["minor_mm"] / 2 if math.isfinite(values["minor_mm"]) else 1.0
        ex, ey = ma * np.cos(phi), mi * np.sin(phi)
        pts = np.stack([values["x_mm"] + ex * math.cos(a) - ey * math.sin(a),
                        values["y_mm"] + ex * math.sin(a) + ey * math.cos(a)], 1)
        uv = t.layout_to_image(np.vstack([[values["x_mm"], values["y_mm"]], pts]))
        sliding = values.pop("sliding") == 1.0
        out: dict[str, Any] = {k2: (round(v, 3) if math.isfinite(v) else None) for k2, v in values.items()}
        out.update(shape=b.shapes[k], u=round(float(uv[0, 0]), 1), v=round(float(uv[0, 1]), 1),
                   outline=np.round(uv[1:], 1).tolist(), sliding=sliding,
                   arrow=contact_arrow(self.bundle.transform, values, sliding))
        return out

    def _state(self, b: _Buffers, surface: np.ndarray, contacts: list[dict[str, Any]]) -> dict[str, Any]:
        means = b.means
        live = ~self.bundle.fibers.dead
        median = float(np.median(means[live])) if live.any() else 0.0
        ids = self.bundle.layout.ids
        dark = [int(i) for i in ids[live & (means < DARK_FRACTION * median)]]
        saturated = [int(i) for i in ids[live & (means >= SATURATED_LEVEL)]]
        top = float(surface.max(initial=0.0))
        scaled = np.zeros(surface.shape, np.uint8) if top <= 0 else np.clip(surface / top * 255, 0, 255).astype(np.uint8)
        stats = {("contact_frames" if k == "contacts" else k): int(v) for k, v in zip(STAT_FIELDS, b.stats)}
        return {
            "seq": self._seq, "t_ns": b.t_ns, "fps": round(b.fps, 1), **stats, "view_skipped": self.skipped,
            "link": self.link(), "baseline_ready": b.baseline_ready, "truncation": round(b.trunc, 4),
            "levels": base64.b64encode(np.clip(np.rint(means), 0, 255).astype(np.uint8).tobytes()).decode(),
            "dark": dark, "saturated": saturated,
            "dark_level": round(DARK_FRACTION * median, 1), "saturated_level": SATURATED_LEVEL,
            "surface": {"n": int(surface.shape[0]), "max": round(top, 4),
                        "values": base64.b64encode(scaled.tobytes()).decode()},
            "contacts": contacts, "message": self.message,
            "vibration": round(b.vibration, 2) if math.isfinite(b.vibration) else None, "vibrating": b.vibrating,
            "orient": {"active": self.procedure is not None,
                       "prompt": self.procedure.prompt if self.procedure is not None else ""},
        }

    def layout_json(self) -> bytes:
        """The fiber map for the overlay: frame size, each fiber's centre, radius, id, dead; unmatched blobs."""
        t = self.bundle.fibers
        radius = np.sqrt(t.pixel_count / math.pi)
        fibers = [{"id": int(i), "u": round(float(c[0]), 1), "v": round(float(c[1]), 1), "r": round(float(r), 1),
                   "dead": bool(d)} for i, c, r, d in zip(self.bundle.layout.ids, t.centroid_px, radius, t.dead)]
        grid = self.bundle.grid
        reach = 0.45 * self.bundle.layout.radius_mm  # the sensor's +x and +y, drawn from its centre
        origin, ex, ey = self.bundle.transform.layout_to_image(np.array([[0.0, 0.0], [reach, 0.0], [0.0, reach]]))
        return json.dumps({"width": t.width, "height": t.height, "fibers": fibers,
                           "unmatched": np.round(t.unmatched_px, 1).tolist(),
                           "calibration_id": self.bundle.calibration_id,
                           "axes": {"origin": np.round(origin, 1).tolist(), "x": np.round(ex, 1).tolist(),
                                    "y": np.round(ey, 1).tolist()},
                           "grid": {"n": grid.n, "x0_mm": grid.x0_mm, "y0_mm": grid.y0_mm,
                                    "step_mm": grid.step_mm}},
                          separators=(",", ":")).encode()

    # -- the guided orientation -----------------------------------------------------------------

    def start_orientation(self) -> str:
        """Start the guided orientation (press near +x, then +y); the prompt is in every update."""
        from optitac_edge.calibration.edge_presses import EdgePresses

        self.procedure = EdgePresses(self.bundle.layout)
        self._tell(self.procedure.prompt)
        return "orientation: " + self.procedure.prompt

    def cancel_orientation(self) -> str:
        self.procedure = None
        self._tell("")
        return "orientation cancelled"

    def _tell(self, prompt: str) -> None:
        if self.on_prompt is not None:
            self.on_prompt(prompt)

    def _oriented(self, fit: OrientationFit | None) -> str:
        """Write the result into the bundle (file, when there is one) and hand the loop the new fiber map."""
        from optitac_edge.calibration.orientation import reorient_bundle
        from optitac_edge.core.pipeline import Pipeline

        if fit is None or fit.symmetry is None:
            return f"orientation not decided: {'no fit' if fit is None else fit.reason}"
        evidence = f"edge presses in the view, RMS {fit.best_rmse_mm:.1f} mm"
        bundle = reorient_bundle(self.bundle, fit.symmetry, evidence)
        where = "kept in memory"
        if self.bundle_path is not None:
            from optitac_edge.io.bundle_file import save_bundle

            try:
                bundle = save_bundle(bundle, self.bundle_path)
                where = f"saved to {self.bundle_path}"
            except OptiTacError as exc:
                where = f"not saved ({exc})"
        self.bundle = bundle
        pipeline = Pipeline(bundle)  # built here, off the frame thread; the loop only swaps it in
        self.actions.append(("swap", pipeline))
        what = "confirmed" if fit.symmetry.is_identity else f"corrected (the fiber map was {fit.symmetry.label})"
        return f"orientation {what}; {where}"

    def close(self) -> None:
        """Stop the worker (idempotent)."""
        self._stop.set()
        self._wake.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    def wait_published(self, after_seq: int = 0, timeout_s: float = 5.0) -> Published | None:
        """The first update after ``after_seq`` (tests and ``snapshot``), or None after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        with self._published:
            while True:
                p = self.published
                if p is not None and p.seq > after_seq:
                    return p
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._published.wait(left)
