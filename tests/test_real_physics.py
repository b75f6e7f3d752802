"""The ``real`` physics (issue 37): the statistics a real 61-fiber sensor showed, in the simulator."""

from __future__ import annotations

import numpy as np
import pytest

from optitac_edge.core.layout import hex_layout
from optitac_edge.io.recording import Recording
from optitac_edge.sim.physics import physics
from optitac_edge.sim.real import FiberColours, FiberWander, WanderingLight
from optitac_edge.sim.scenarios import write_scenario


def test_the_fibers_wander_as_the_real_ones_did() -> None:
    """Over five minutes, across the 61 fibers (the median of 30 sensors): a median change of about 2 %, a
    90th percentile of about 6 %, the largest about 12 % (the real sensor: 2.0, 5.9, 12.3 %)."""
    layout = hex_layout(4, 4.0)
    medians, p90, top = [], [], []
    for seed in range(30):
        light = WanderingLight(layout, FiberWander(), sensor_seed=seed, day=0, session_seed=seed)
        d = np.abs(light.factor(400.0) / light.factor(100.0) - 1.0)
        medians.append(np.median(d))
        p90.append(np.percentile(d, 90))
        top.append(d.max())
    assert 0.017 < np.median(medians) < 0.025
    assert 0.048 < np.median(p90) < 0.07
    assert 0.10 < np.median(top) < 0.16


def test_days_change_each_fibers_light_by_up_to_thirty_percent_and_one_fiber_jumps() -> None:
    layout = hex_layout(4, 4.0)
    day0 = WanderingLight(layout, FiberWander(), 7, day=0, session_seed=1)
    day3 = WanderingLight(layout, FiberWander(), 7, day=3, session_seed=1)
    assert np.all(day0.day_gain == 1.0)
    assert 0.7 <= day3.day_gain.min() < 0.95 and 1.05 < day3.day_gain.max() <= 1.3
    still = WanderingLight(layout, FiberWander(five_min=0.0, five_min_outer=0.0), 7, 0, 1)
    late = still.factor(2400.0)  # 40 minutes in: the jump has run its course
    assert np.count_nonzero(np.abs(late - 1) > 1e-9) == 1 and late.max() == pytest.approx(1.39)
    assert np.allclose(still.factor(500.0), 1.0)  # not yet


def test_a_press_changes_a_colour_coded_fibers_chromaticity_not_by_itself_its_luma() -> None:
    colours = FiberColours.draw(61, sensor_seed=3)
    luma = np.array([0.299, 0.587, 0.114])
    np.testing.assert_allclose(colours.shifts @ luma, 0.0, atol=1e-12)
    at_rest, pressed = colours.rgb(np.zeros(61)), colours.rgb(np.full(61, 0.5))
    np.testing.assert_allclose(pressed @ luma, at_rest @ luma)
    chroma = pressed / pressed.sum(axis=1, keepdims=True) - at_rest / at_rest.sum(axis=1, keepdims=True)
    assert np.all(np.abs(chroma).sum(axis=1) > 0.01)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    return Recording(write_scenario(tmp_path_factory.mktemp("real") / "s", "snapshots", seed=1, day=1,
                                    physics="real"))


def test_a_snapshot_session_of_the_real_physics(session) -> None:
    """An hour of RGB snapshots of the 61-fiber array 20 s apart, the baseline taken again every 5 minutes
    (listed as tares), presses of 1-12 N of force with their truth, stray light in the corners."""
    rec = session
    assert rec.pixel_format == "rgb" and rec.meta.rest_frames == 10
    meta = rec.meta.extra["simulator"]
    assert len(meta["fiber_centres_px"]) == 61 and meta["physics"] == "real"
    t = rec.t_ns / 1e9
    assert 3000 < t[-1] < 3700 and np.median(np.diff(t[10:])) > 10
    assert len(rec.tares) >= 10 and all(tare.frames == 3 for tare in rec.tares)
    truth = rec.truth
    assert truth is not None and truth.force_n is not None
    force = truth.force_n[truth.contact]
    assert truth.contact.sum() > 100 and (~truth.contact).sum() > 30 and 0.5 < force.min() and force.max() < 15
    corner = np.asarray(rec.frames[0])[17:28, 17:28].mean()  # the blob at (22, 22), 8 px, +2.5
    middle = np.asarray(rec.frames[0])[100:125, 5:30].mean()
    assert corner > middle + 1.5  # a dim blob of stray light
    assert physics("real").array == (4, 4.0)
