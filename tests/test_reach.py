"""How far the experiments press on an array: the paper's as the paper's, a wider one on its fibers."""

from __future__ import annotations

import numpy as np
import pytest

from optitac_edge.bringup.experiments import plan
from optitac_edge.core.layout import hex_layout
from optitac_edge.core.reach import axis_reach_mm, depth_points, depth_rings


def _lines(layout) -> tuple[float, float, int]:
    presses = plan("unseen", layout)
    xs = [abs(p.x_mm) for p in presses if p.y_mm == 0.0]
    ys = [abs(p.y_mm) for p in presses if p.x_mm == 0.0]
    return max(xs), max(ys), len(presses)


@pytest.mark.parametrize("rings, pitch, reach, presses, rings_mm", [
    (8, 1.5, 9.0, 146, [6.0]),  # the paper's array: its experiments as they were
    (4, 4.0, 7.8, 50, [8.0]),   # 61 fibers at 4 mm: as they were
])
def test_the_paper_sized_arrays_keep_their_experiments(rings, pitch, reach, presses, rings_mm) -> None:
    layout = hex_layout(rings, pitch)
    x, y, n = _lines(layout)
    assert (x, y, n) == (pytest.approx(reach), pytest.approx(reach), presses)
    assert depth_rings(layout) == pytest.approx(rings_mm)
    assert len(plan("depths", layout)) == 112


def test_a_wide_array_is_pressed_on_its_fibers_and_its_depths_reach_as_far() -> None:
    """1027 fibers at 1.5 mm: the rows reach 23.4 mm along y (27 mm along x); the y line of ``unseen`` stops
    half a pitch inside them (it went to 24 mm, off the fibers, where no depth model can follow), and
    ``depths`` adds a ring 24 mm out to the one at 13.5 mm."""
    layout = hex_layout(18, 1.5)
    assert axis_reach_mm(layout, 0) == pytest.approx(27.0)
    assert axis_reach_mm(layout, 1) == pytest.approx(18 * 1.5 * np.sqrt(3) / 2)
    x, y, _ = _lines(layout)
    assert x == pytest.approx(24.0) and y == pytest.approx(22.5) and y <= axis_reach_mm(layout, 1) - 0.75
    assert depth_rings(layout) == pytest.approx([13.5, 24.0])
    radii = sorted({round(float(np.hypot(p.x_mm, p.y_mm)), 6) for p in plan("depths", layout)})
    assert radii == pytest.approx([0.0, 13.5, 24.0])


@pytest.mark.parametrize("rings, pitch", [(8, 1.5), (4, 4.0), (18, 1.5)])
def test_the_rig_and_the_simulator_press_the_same_depth_points(rings, pitch) -> None:
    """The bring-up's ``depths`` plan and the simulator's ``depths`` scenario press at the same places, the
    centre and 6 points on each depth ring, each at every depth twice (one function places them for both)."""
    from optitac_edge.sim.scenarios import schedule

    layout = hex_layout(rings, pitch)
    points = depth_points(layout)
    assert len(points) == 1 + 6 * len(depth_rings(layout)) and points[0] == (0.0, 0.0)
    assert np.hypot(*np.array(points[1:]).T) == pytest.approx(np.repeat(depth_rings(layout), 6))
    rig = sorted((p.x_mm, p.y_mm, p.depth_mm) for p in plan("depths", layout))
    presses = schedule("depths", seed=0, layout=layout)
    sim = sorted((p.x_mm, p.y_mm, p.depth_mm) for k, p in enumerate(presses) if p is not None and presses[k - 1] is None)
    assert rig == sim and len(rig) == len(points) * 8 * 2
