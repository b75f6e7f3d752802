"""Frames far apart in time are independent snapshots: nothing is carried across a gap longer than
``ContactOptions.gap_s`` (issue 37: a labelled data set's frames are seconds to minutes apart)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optitac_edge.core.pipeline import Pipeline
from optitac_edge.io.bundle_file import load_bundle
from optitac_edge.sim.sensor import SimulatedSensor
from optitac_edge.sim.skin import Indenter

PERIOD = 16_666_667  # ns, 60 fps
GAP = 30_000_000_000  # ns: half a minute


@pytest.fixture(scope="module")
def bundle(bundle_path):
    return load_bundle(bundle_path)


def _frames(presses: list[Indenter | None], seed: int = 0) -> list[np.ndarray]:
    sensor = SimulatedSensor(seed=seed)
    return [sensor.frame(() if p is None else (p,)) for p in presses]


def _times(n_before: int, n_after: int) -> list[int]:
    before = [k * PERIOD for k in range(n_before)]
    return before + [before[-1] + GAP + k * PERIOD for k in range(n_after)]


@pytest.mark.parametrize("compiled", [False, True])
def test_a_press_after_a_gap_is_a_new_touch_with_no_velocity(bundle, compiled) -> None:
    """A press held before a half-minute gap and another after it 4 mm away: the one after it gets a new id,
    touches in its first frame with no velocity (the window does not reach across), and the one before is
    released in that frame. Without the gap the 4 mm step is one contact moving (the tracking gate)."""
    a, b = Indenter("circle", 1.0, 0.0, size_mm=5.0, depth_mm=3.0), Indenter("circle", 5.0, 0.0, size_mm=5.0,
                                                                           depth_mm=3.0)
    frames = _frames([None] * 10 + [a] * 8 + [b] * 8)
    for gap in (True, False):
        pipe = Pipeline(bundle, compiled=compiled)
        times = _times(18, 8) if gap else [k * PERIOD for k in range(26)]
        ids, velocities, released = [], [], []
        for frame, t in zip(frames, times):
            r = pipe.process_recorded(frame, t)
            ids.append(r.primary.contact_id)
            velocities.append(r.primary.vx_mm_s)
            released.append(r.releases())
        assert ids[10] != 0 and len(set(ids[10:18])) == 1 and len(set(ids[18:])) == 1
        if gap:
            assert ids[18] != ids[10] and pipe.after_gap is False
            assert math.isnan(velocities[18]) and released[18] == [(ids[10], 10)]
            assert pipe.result.primary.touch_frame == 18
        else:
            assert ids[18] == ids[10] and released[18] == []


@pytest.mark.parametrize("compiled", [False, True])
def test_no_hysteresis_across_a_gap(bundle, compiled) -> None:
    """A press faded to a strength between the off and on levels stays a contact while the frames run on
    (hysteresis), but the same frame after a gap is judged afresh against the on level: no contact."""
    sensor = SimulatedSensor(seed=0)
    deep = sensor.darkening((Indenter("circle", 0.0, 0.0, size_mm=5.0, depth_mm=3.0),))
    frames = [sensor.frame() for _ in range(10)] + [sensor.frame_from_darkening(deep) for _ in range(5)]
    pipe = Pipeline(bundle, compiled=compiled)
    for k, frame in enumerate(frames):
        pipe.process_recorded(frame, k * PERIOD)
    assert pipe.result.n_contacts == 1
    _trunc, off, on = pipe.levels.as_tuple()
    assert off < on
    faint = sensor.frame_from_darkening(deep * (0.5 * (off + on) / float(deep.max())))
    t = 15 * PERIOD
    pipe.process_recorded(faint, t)
    assert pipe.result.n_contacts == 1 and off < float(pipe.surface.max()) < on  # held on by hysteresis
    assert pipe.process_recorded(faint, t + GAP).n_contacts == 0  # a snapshot: the on level again
    assert pipe.after_gap


@pytest.mark.parametrize("compiled", [False, True])
def test_the_baseline_takes_no_tracking_step_across_a_gap(bundle, compiled) -> None:
    """A quiet frame 1 % brighter per fiber half a minute later: the tracking step was capped at one time
    constant (63 % of the way) and taken; across the gap it is not taken. The next frames track again."""
    pipe = Pipeline(bundle, compiled=compiled)
    rest = _frames([None] * 12)
    for k, frame in enumerate(rest[:10]):
        pipe.process_recorded(frame, k * PERIOD)
    before = pipe.baseline.values.copy()
    brighter = [np.clip(np.rint(f.astype(np.float32) * 1.01), 0, 255).astype(np.uint8) for f in rest[10:]]
    pipe.process_recorded(brighter[0], 9 * PERIOD + GAP)
    assert pipe.after_gap and pipe.result.n_contacts == 0
    np.testing.assert_array_equal(pipe.baseline.values, before)
    pipe.process_recorded(brighter[1], 10 * PERIOD + GAP)
    assert not pipe.after_gap and not np.array_equal(pipe.baseline.values, before)
