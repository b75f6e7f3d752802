"""Snapshot sessions: frames seconds to minutes apart, as a labelled data set or a rig that photographs each
press gives them (the ``snapshots`` scenario).

A session starts with :data:`LEAD_FRAMES` contact-free frames a second apart (the fiber map and the first
baseline), then every :data:`EVERY_S` seconds (a few seconds' jitter) a snapshot: a press (a circle of
the experiments' size for the array, anywhere on it, 0.5-2.5 mm deep, its force from the load cell's model)
or, one in four, the skin at rest. The presses' centres reach the outermost fibers (a press there is
partly off the array, as on a real sensor). Every :data:`TARE_EVERY_S` the baseline is taken again from
:data:`TARE_FRAMES` contact-free frames a second apart, listed in ``meta.json``'s ``tares``. Nothing but
the times joins one snapshot to the next: the pipeline treats frames further apart than its ``gap_s`` as
independent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from optitac_edge.core.layout import FiberLayout, pitch_scale, scaled_mm
from optitac_edge.sim.skin import Indenter

#: The scenarios of snapshots (``optitac-edge sim --scenario``).
SNAPSHOT_SCENARIOS = ("snapshots",)
#: Contact-free frames at the start, a second apart.
LEAD_FRAMES = 10
#: A snapshot every this many seconds (+- a fifth), and the session's default length, s.
EVERY_S = 20.0
SESSION_S = 3600.0
#: The baseline is taken again this often, from this many contact-free frames a second apart.
TARE_EVERY_S = 300.0
TARE_FRAMES = 3
#: Of the snapshots, this fraction is of the skin at rest.
REST_FRACTION = 0.25
#: The presses' depths, mm.
DEPTH_RANGE_MM = (0.5, 2.5)


@dataclass(frozen=True)
class Snapshot:
    """One frame of a session: its time (s), what presses (None: rest), and whether it is scored (the tares'
    frames are the baseline, not scored)."""

    t_s: float
    press: Indenter | None
    scored: bool


def snapshot_session(layout: FiberLayout, seed: int, session_s: float = SESSION_S, frames: int | None = None
                     ) -> tuple[list[Snapshot], list[dict[str, int]]]:
    """The frames of a session and its tares (``{"frame": F, "frames": TARE_FRAMES}``); ``frames``: only the
    first so many."""
    rng = np.random.default_rng([seed, 41])
    size = scaled_mm(5.0, pitch_scale(layout))
    room = layout.radius_mm
    out_frames = [Snapshot(float(k), None, False) for k in range(LEAD_FRAMES)]
    tares: list[dict[str, int]] = []
    t, next_tare = float(LEAD_FRAMES) + EVERY_S, TARE_EVERY_S
    while t < session_s:
        if t >= next_tare:
            tares.append({"frame": len(out_frames), "frames": TARE_FRAMES})
            out_frames += [Snapshot(t + k, None, False) for k in range(TARE_FRAMES)]
            t += TARE_FRAMES + EVERY_S / 2
            next_tare += TARE_EVERY_S
        if rng.random() < REST_FRACTION:
            out_frames.append(Snapshot(t, None, True))
        else:
            r, a = room * math.sqrt(rng.random()), rng.uniform(0.0, 2 * math.pi)
            depth = float(rng.uniform(*DEPTH_RANGE_MM))
            out_frames.append(Snapshot(t, Indenter("circle", r * math.cos(a), r * math.sin(a), 0.0, size, depth),
                                       True))
        t += EVERY_S * float(rng.uniform(0.8, 1.2))
    if frames is not None:
        kept = max(int(frames), LEAD_FRAMES)
        return out_frames[:kept], [tare for tare in tares if tare["frame"] + TARE_FRAMES <= kept]
    return out_frames, tares
