"""The guided orientation procedure: press near +x, then near +y (a pure state machine)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optitac_edge.calibration.edge_presses import EdgePresses, resolve_edge_presses
from optitac_edge.calibration.orientation import layout_symmetries
from optitac_edge.core.layout import hex_layout

FRAME_NS = 16_666_667


def _feed(proc: EdgePresses, t: int, frames: int, xy: tuple[float, float] | None, jitter: float = 0.0,
          seed: int = 0) -> int:
    rng = np.random.default_rng(seed)
    for _ in range(frames):
        if xy is None:
            proc.feed(False, math.nan, math.nan, t)
        else:
            proc.feed(True, xy[0] + rng.normal(0, jitter), xy[1] + rng.normal(0, jitter), t)
        t += FRAME_NS
    return t


@pytest.mark.parametrize("k", range(12))
@pytest.mark.parametrize("off_deg", (-22.0, 0.0, 22.0))
def test_two_edge_presses_read_through_any_symmetry_give_it(k, off_deg) -> None:
    layout = hex_layout()
    h = layout_symmetries(layout)[k]
    proc = EdgePresses(layout)
    r = 0.8 * layout.radius_mm
    t = _feed(proc, 0, 30, None)
    assert "+x" in proc.prompt
    for step, angle in enumerate((0.0, 90.0)):
        a = math.radians(angle + off_deg)
        seen = h.apply(np.array([[r * math.cos(a), r * math.sin(a)]]))[0]  # where the bundle reads the press
        t = _feed(proc, t, 60, (seen[0], seen[1]), jitter=0.2, seed=step)
        assert proc.prompt == "release" and len(proc.taken) == step + 1
        t = _feed(proc, t, 30, None)
    assert proc.done and proc.fit is not None and proc.fit.symmetry is not None
    assert proc.fit.symmetry.label == h.label
    assert proc.prompt == f"done: the fiber map is {h.label}"


def test_a_press_near_the_centre_is_not_taken() -> None:
    proc = EdgePresses(hex_layout())
    t = _feed(proc, 0, 60, (0.5, 1.0))
    assert "too near the centre" in proc.prompt and proc.taken == []
    _feed(proc, t, 30, None)
    assert "+x" in proc.prompt


def test_a_moving_press_is_not_taken_until_it_is_held_still() -> None:
    proc = EdgePresses(hex_layout())
    t = 0
    for i in range(60):  # sliding 0.3 mm a frame
        proc.feed(True, 3.0 + 0.3 * i, 0.0, t)
        t += FRAME_NS
    assert proc.taken == []
    _feed(proc, t, 40, (9.0, 0.0))
    assert proc.taken == [(9.0, 0.0)]


def test_presses_in_the_wrong_places_are_refused_not_guessed() -> None:
    layout = hex_layout()
    r = 0.8 * layout.radius_mm
    fit = resolve_edge_presses(np.array([[r, 0.0], [r * math.cos(math.radians(30)), r * math.sin(math.radians(30))]]),
                               layout)  # +y pressed 30 degrees from +x: between two symmetries
    assert fit.symmetry is None and fit.reason
