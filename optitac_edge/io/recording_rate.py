"""A recording's frame rate, as its capture times show it: the check its readers make and the rate its writers
state (one module for both: :mod:`optitac_edge.io.recording` and :mod:`optitac_edge.io.recording_mcap`)."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from optitac_edge.errors import RecordingError

log = logging.getLogger(__name__)

#: The frame rates a recording may claim, frames/s.
FPS_RANGE = (0.1, 10_000.0)
#: A recording's stated rate must be within this factor of the rate its capture times show.
FPS_TOLERANCE = 1.25
#: Fewer frame intervals than this do not measure a rate (the stated one is taken as it is).
MIN_RATE_INTERVALS = 8
#: Frames at least this far apart are snapshots, each processed on its own, so no rate is used (the contact
#: options' default ``gap_s``).
SNAPSHOT_GAP_NS = 500_000_000


def _rate_gap_ns(fps: float, t_ns: np.ndarray) -> float | None:
    """The frame interval ``t_ns`` shows when it denies ``fps`` (see :func:`check_stated_rate`), else None."""
    if t_ns.shape[0] - 1 < MIN_RATE_INTERVALS:
        return None
    gap_ns = float(np.percentile(np.diff(t_ns), 25))
    period_ns = 1e9 / fps
    if gap_ns >= SNAPSHOT_GAP_NS or period_ns / FPS_TOLERANCE <= gap_ns <= period_ns * FPS_TOLERANCE:
        return None
    return gap_ns


def shown_rate(fps: float, t_ns: np.ndarray) -> float | None:
    """For a writer: the rate, frames/s, a recording's capture times ``t_ns`` show when they deny the stated
    ``fps`` and the rate is one a recording may claim (:data:`FPS_RANGE`); None when they agree (or cannot
    tell). A camera asked for 60 fps may deliver 30 (auto exposure in dim light): the recording says 30."""
    gap_ns = _rate_gap_ns(fps, t_ns)
    if gap_ns is None or gap_ns <= 0 or not FPS_RANGE[0] <= 1e9 / gap_ns <= FPS_RANGE[1]:
        return None
    return round(1e9 / gap_ns, 3)


#: The key a writer keeps the asked-for rate under when it states the rate the frames show.
FPS_ASKED_KEY = "fps_asked"


def state_rate_shown(meta: dict[str, Any], t_ns: np.ndarray, where: Path) -> None:
    """For a writer, before it writes ``meta`` (``meta.json``'s keys): where the capture times ``t_ns`` show
    another rate than ``meta["fps"]`` (:func:`shown_rate`), state that one, keep the asked one under
    :data:`FPS_ASKED_KEY` and warn once."""
    fps = meta.get("fps")
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not (math.isfinite(fps) and fps > 0):
        return  # not a rate: the reader refuses it by its own check
    rate = shown_rate(float(fps), t_ns)
    if rate is None:
        return
    log.warning("%s: the camera delivered %.4g frames/s, not the %g asked for (auto exposure in dim light?): the "
                "recording says %.4g", where, rate, meta["fps"], rate)
    meta[FPS_ASKED_KEY], meta["fps"] = meta["fps"], rate


def check_stated_rate(fps: float, t_ns: np.ndarray, where: Path) -> None:
    """The stated ``fps`` agrees with the capture times ``t_ns`` (int64 ns, shape (N,)).

    The rate shown is the lower quartile of the frame intervals, so a recording that lost frames (even most
    of them, so long as a quarter of its intervals are one period) still shows its camera's period; motion
    and vibration are computed at the stated rate. Snapshots (that quartile :data:`SNAPSHOT_GAP_NS` or
    more) are processed one by one: their stated rate is not used. Writers state the rate the times show
    (:func:`shown_rate`), so a recording this refuses was edited or is not a camera's.

    Raises
    ------
    RecordingError
        The intervals' lower quartile is more than :data:`FPS_TOLERANCE` times off the stated period (an
        edited ``fps``, or times that are not a camera's: all 1 ns apart, say).
    """
    gap_ns = _rate_gap_ns(fps, t_ns)
    if gap_ns is not None:
        shown = f"{1e9 / gap_ns:.4g} fps" if gap_ns > 0 else "no rate: frames at one time"
        raise RecordingError(f"{where}: 'fps' is {fps:g} but its frames are {gap_ns / 1e6:.4g} ms apart ({shown}, "
                             f"lower quartile of {t_ns.shape[0] - 1} intervals): the rate or the times are wrong")


