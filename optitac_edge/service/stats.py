"""The frame loop's counters, and the rate-limited log line of each fault and event it counts.

Every function here counts one event into :class:`ServiceStats` (and the
sensor's STATUS flags) and logs it the first time and every 100th: the loop
never logs per frame.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from optitac_edge.core.frame_engine import Skip
from optitac_edge.errors import CameraError

if TYPE_CHECKING:
    from optitac_edge.service.channel import SensorChannel

#: The frame loop's logger: these lines are the loop's, and keep its name in the journal.
log = logging.getLogger("optitac_edge.service.loop")


@dataclass
class ServiceStats:
    """Counters of one run.

    ``camera_errors`` counts every frame fault (read errors and timeouts, wrong
    frames, dark and saturated frames); the other counters split it by kind.
    With several sensors on the camera, ``frames`` counts camera frames some
    sensor processed, ``contacts`` every sensor's frames with a contact, and a
    dark or saturated patch counts once per sensor it hides.
    """

    frames: int = 0
    #: Camera frames the loop read, processed or not (``run --frames N`` stops after N of them).
    frames_read: int = 0
    contacts: int = 0
    sent: int = 0
    frames_dropped: int = 0
    #: Frames the camera lost before the loop caught up with it (it streamed while the bundles were made).
    frames_dropped_before_loop: int = 0
    camera_errors: int = 0
    read_errors: int = 0  # CameraError from read(): timeouts, device gone, driver errors
    unexpected_errors: int = 0  # any other exception from the camera (a backend bug): counted like read_errors
    bad_frames: int = 0  # wrong shape or dtype
    dark_frames: int = 0
    saturated_frames: int = 0  # skipped: most fibers at full scale
    mismatched_frames: int = 0  # skipped: not of the bundle's sensor (core/fingerprint.py)
    saturated_sent: int = 0  # processed frames with some fiber at full scale (SATURATED flag)
    light_changes: int = 0  # common-mode changes of the light (LED dimming), not reported as contacts
    baseline_raises: int = 0  # fibers brighter than their baseline (taken over a press): raised to their light
    processing_errors: int = 0  # frames the pipeline failed on (a bug): counted, flagged, baseline re-taken
    protocol_refused: int = 0  # SET_PROTOCOL for a version the link cannot speak: ignored
    stalls: int = 0  # gaps without a good frame longer than watchdog.max_frame_gap_s ridden out (view)
    reopens: int = 0  # successful camera reopens
    reopen_failures: int = 0
    commands: dict[str, int] = field(default_factory=dict)
    started_ns: int = 0
    #: The frame rate over the last status period (:meth:`measure_rate`), frames/s.
    recent_fps: float = 0.0
    _rate_mark: tuple[int, int] | None = None

    def fps(self, now_ns: int) -> float:
        """Frames per second since the start (the run's summary)."""
        elapsed = (now_ns - self.started_ns) / 1e9
        return self.frames / elapsed if elapsed > 0 else 0.0

    def measure_rate(self, now_ns: int) -> float:
        """The frame rate since the previous call (or the start), kept as :attr:`recent_fps`: what STATUS says.

        The average since the start over-read for a long time after it (the frames queued while the
        service started come at once: 85 fps, then 62, on a 60-fps camera).
        """
        since_ns, since_frames = self._rate_mark or (self.started_ns, 0)
        if now_ns - since_ns >= 200_000_000 or self._rate_mark is None:
            span = (now_ns - since_ns) / 1e9
            self.recent_fps = (self.frames - since_frames) / span if span > 0 else 0.0
            self._rate_mark = (now_ns, self.frames)
        return self.recent_fps


def _due(count: int) -> bool:
    """Log the first and every 100th."""
    return count == 1 or count % 100 == 0


def camera_failed(st: ServiceStats, exc: Exception) -> None:
    """A read that raised: a camera error (a backend bug when not a :class:`CameraError`)."""
    st.camera_errors += 1
    if isinstance(exc, CameraError):
        st.read_errors += 1
    else:
        st.unexpected_errors += 1
    if _due(st.camera_errors):
        log.warning("camera error %d: %s: %s", st.camera_errors, type(exc).__name__, exc)


def frame_skipped(st: ServiceStats, ch: SensorChannel, why: Skip) -> None:
    """A frame the check refused for this sensor: bad, dark or saturated; or not of its bundle's sensor
    (counted apart: the camera is working, the channel said why once)."""
    ch.fault_since_status = True
    if why is Skip.MISMATCH:
        st.mismatched_frames += 1
        return
    st.camera_errors += 1
    if why is Skip.BAD:
        st.bad_frames += 1
    elif why is Skip.DARK:
        st.dark_frames += 1
    else:
        st.saturated_frames += 1
    if _due(st.camera_errors):
        log.warning("camera fault %d: %s frame skipped (sensor %d)", st.camera_errors, why, ch.sensor_id)


def processing_failed(st: ServiceStats, ch: SensorChannel, exc: Exception) -> None:
    """A frame the pipeline failed on: counted, flagged, and its state started afresh (a new baseline)."""
    st.processing_errors += 1
    ch.fault_since_status = True
    if _due(st.processing_errors):
        log.error("processing error %d (sensor %d): %s: %s; the baseline is taken again", st.processing_errors,
                  ch.sensor_id, type(exc).__name__, exc)
    ch.pipeline.reset_baseline()


def light_changed(st: ServiceStats, ch: SensorChannel) -> None:
    """A common-mode change of the light (not a contact)."""
    st.light_changes += 1
    ch.light_since_status = True
    if _due(st.light_changes):
        log.warning("common-mode change of the light %d (LED dimming or brightening to %.3f of the "
                    "baseline, sensor %d): not a contact", st.light_changes, _gain(ch), ch.sensor_id)


def baseline_raised(st: ServiceStats, ch: SensorChannel, fibers: int) -> None:
    """Fibers brighter than their baseline: it had been taken over a press."""
    st.baseline_raises += 1
    if _due(st.baseline_raises):
        log.warning("baseline raised %d (sensor %d): %d fibers stayed brighter than their baseline, which no "
                    "press can make: it was taken while the skin was pressed there (a start or a tare during "
                    "a grasp); their baseline is now their light", st.baseline_raises, ch.sensor_id, fibers)


def _gain(ch: SensorChannel) -> float:
    """The sensor's LED gain relative to its baseline (1 without gain compensation)."""
    led = ch.pipeline.led_gain
    return 1.0 if led is None else led.gain
