"""How well a recording's contact motion and vibration were found, against the truth's motion columns.

A recording of the simulator's ``slide``, ``vibrate`` or ``hold`` scenario (or any whose ``truth.csv``
has :data:`~optitac_edge.io.recording.MOTION_COLUMNS`) measured with
:func:`~optitac_edge.calibration.measure.measure_recording` gives:

* the velocity error (RMSE of the estimated against the true velocity, mm/s) over the frames whose whole
  velocity window saw one steady true velocity (within 5 %; the window's first frames after a start, a
  stop or a turn are a transient of the estimator by construction, and are left out), per speed (to
  0.5 mm/s);
* each slide's onset latency: how many frames of sliding the estimate had seen when it first reported
  ``sliding`` with a slide frame within the slide (None: never found);
* false slips: slide onsets in frames the truth says are pressed in, held, shaken or lifted, with the
  seconds of contact they were counted over;
* contacts sliding far: the number of ids the estimate gave each press (1: it kept its id);
* each shake's latency to the vibration event (frames of shaking seen, None: not found) and vibration
  events in quiet holds (frames held for at least :data:`SETTLED_FRAMES` since the press settled, a slide
  or a shake).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from optitac_edge.calibration.measure import Measurements
from optitac_edge.core.motion import WINDOW
from optitac_edge.io.recording import Truth

#: Frames of a quiet hold before a vibration event there counts as false (0.25 s at 240 fps).
SETTLED_FRAMES = 60


@dataclass(frozen=True)
class MotionReport:
    """See the module's description."""

    velocity_rmse_mm_s: float
    velocity_rmse_by_speed: dict[float, tuple[int, float]]  # speed -> (frames, RMSE)
    onsets: list[tuple[float, int | None]]  # (speed, frames of sliding seen when found)
    false_slips: int
    held_s: float
    ids_per_press: list[int]
    shakes: list[int | None]  # frames of shaking seen when the event came
    false_vibrations: int
    quiet_s: float


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, end) of every run of True, end exclusive."""
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(np.int8), 0]))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))


def motion_report(m: Measurements, truth: Truth, fps: float) -> MotionReport | None:
    """The motion metrics of a measured recording; None when the truth or the measurements have no motion."""
    if truth.motion is None or truth.vx_mm_s is None or truth.vy_mm_s is None or m.motion is None:
        return None
    mo, n = m.motion, len(m)
    rows = truth.frame
    state = np.full(n, "", dtype=object)
    tv = np.full((n, 2), np.nan)
    state[rows] = truth.motion
    tv[rows, 0], tv[rows, 1] = truth.vx_mm_s, truth.vy_mm_s
    ev = np.c_[mo.vx_mm_s, mo.vy_mm_s]
    sliding = state == "sliding"
    steady = sliding.copy()
    true_speed = np.hypot(tv[:, 0], tv[:, 1])
    for k in range(1, WINDOW):  # the whole window at one true velocity (within 5 %: a rig's poses are rounded)
        change = np.hypot(*(tv[k:] - tv[:-k]).T)
        steady[k:] &= sliding[:-k] & (change <= np.maximum(0.05 * true_speed[k:], 0.1))
    steady[:WINDOW - 1] = False
    err2 = np.sum((ev - tv) ** 2, axis=1)
    ok = steady & np.isfinite(err2)
    speed = np.round(true_speed * 2) / 2  # grouped to 0.5 mm/s
    by_speed = {float(s): (int(np.sum(ok & (speed == s))), float(np.sqrt(np.mean(err2[ok & (speed == s)]))))
                for s in np.unique(speed[ok])}
    onsets: list[tuple[float, int | None]] = []
    for start, end in _runs(sliding):
        found = [k for k in range(start, end) if mo.sliding[k] and mo.slide_frame[k] >= start]
        onsets.append((float(speed[(start + end) // 2]), found[0] - start + 1 if found else None))
    onset_frame = mo.sliding & (mo.slide_frame == np.arange(n))
    still = (state == "held") | (state == "vibrating") | (state == "pressing")
    false_slips = int(np.sum(onset_frame & still))
    press = state != ""
    ids = [len(set(mo.contact_id[a:b].tolist()) - {0}) for a, b in _runs(press)]
    quiet = state == "held"
    settled = quiet.copy()
    for a, b in _runs(quiet):
        settled[a:min(a + SETTLED_FRAMES, b)] = False
    shakes: list[int | None] = []
    for start, end in _runs(state == "vibrating"):
        hit = np.flatnonzero(mo.vibrating[start:end])
        shakes.append(int(hit[0]) + 1 if hit.size else None)
    return MotionReport(
        velocity_rmse_mm_s=float(np.sqrt(np.mean(err2[ok]))) if ok.any() else float("nan"),
        velocity_rmse_by_speed=by_speed, onsets=onsets, false_slips=false_slips,
        held_s=float(np.sum(still)) / fps, ids_per_press=ids, shakes=shakes,
        false_vibrations=int(np.sum(mo.vibration_began & settled)), quiet_s=float(np.sum(settled)) / fps)


def format_motion(r: MotionReport) -> list[str]:
    """The report as printable lines."""
    lines = []
    if r.velocity_rmse_by_speed:
        lines.append(f"velocity (steady {WINDOW}-frame windows): RMSE {r.velocity_rmse_mm_s:.2f} mm/s; by speed "
                     + ", ".join(f"{s:g}: {v:.2f} ({k})" for s, (k, v) in r.velocity_rmse_by_speed.items()))
    if r.onsets:
        lines.append("slides found after (frames of sliding; -: never): "
                     + ", ".join(f"{s:g} mm/s {'-' if f is None else f}" for s, f in r.onsets))
    lines.append(f"false slips: {r.false_slips} in {r.held_s:.1f} s not sliding; ids per press: "
                 f"max {max(r.ids_per_press, default=0)} over {len(r.ids_per_press)} presses")
    if r.shakes:
        lines.append("vibration found after (frames of shaking; -: never): "
                     + ", ".join("-" if f is None else str(f) for f in r.shakes))
    lines.append(f"false vibration events: {r.false_vibrations} in {r.quiet_s:.1f} s of quiet holds")
    return lines
