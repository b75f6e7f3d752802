"""Registration of blob centroids to the layout: transform fit and assignment."""

from __future__ import annotations

import numpy as np
import pytest
from test_fiber_synth import Synth, true_centres

from optitac_edge.calibration.fiber_register import lattice_angle_deg, register_blobs
from optitac_edge.core.layout import hex_layout
from optitac_edge.errors import FiberMapError

LAYOUT = hex_layout()


def _points(rot: float, mirror: bool, seed: int = 0) -> tuple[np.ndarray, float]:
    s = Synth(rotation_deg=rot, mirror=mirror)
    c, scale = true_centres(s)
    rng = np.random.default_rng(seed)
    return c + rng.normal(0, 0.3, c.shape), scale


@pytest.mark.parametrize("rot", [0.0, 29.0, 75.0, 143.0, 200.0, 311.0])
@pytest.mark.parametrize("mirror", [False, True])
@pytest.mark.parametrize("hint_error", [-20.0, 20.0])
def test_assigns_every_fiber(rot: float, mirror: bool, hint_error: float) -> None:
    pts, scale = _points(rot, mirror)
    perm = np.random.default_rng(1).permutation(len(pts))  # blobs come in any order
    reg = register_blobs(pts[perm], LAYOUT, rot + hint_error, mirror)
    assert reg.n_found == 217 and reg.unmatched.size == 0
    assert np.array_equal(perm[reg.fiber_blob], np.arange(217))
    t = reg.transform
    assert ((t.rotation_deg - rot + 180.0) % 360.0 - 180.0) == pytest.approx(0.0, abs=0.5)
    assert t.scale_px_per_mm == pytest.approx(scale, rel=0.03)
    assert reg.rms_pitch < 0.05


def test_missing_fibers_and_stray_blobs() -> None:
    pts, _ = _points(40.0, False)
    dead = [0, 16, 108, 109, 216]  # includes the central fiber and rim fibers
    keep = np.setdiff1d(np.arange(217), dead)
    stray = np.array([[5.0, 5.0], [630.0, 470.0]])
    reg = register_blobs(np.vstack([pts[keep], stray]), LAYOUT, 30.0, False)
    assert reg.dead.tolist() == dead
    assert reg.unmatched.tolist() == [len(keep), len(keep) + 1]
    assert np.array_equal(keep[reg.fiber_blob[keep]], keep)


def test_lattice_angle_is_modulo_60() -> None:
    for rot in (0.0, 13.0, 47.0, 95.0, 250.0):
        pts, scale = _points(rot, rot > 90)
        got = lattice_angle_deg(pts, 1.5 * scale)
        assert ((got - rot % 60 + 30) % 60 - 30) == pytest.approx(0.0, abs=1.0)


def test_hint_off_by_60_degrees_misassigns() -> None:
    # Documented limitation: the array is 60-degree symmetric; the hint must be
    # within +-20 degrees. 60 degrees off yields a consistent but rotated assignment.
    pts, _ = _points(10.0, False)
    reg = register_blobs(pts, LAYOUT, 70.0, False)
    assert reg.n_found == 217
    assert not np.array_equal(reg.fiber_blob, np.arange(217))
    assert reg.transform.rotation_deg == pytest.approx(70.0, abs=1.0)


def test_too_few_blobs() -> None:
    with pytest.raises(FiberMapError, match="found 3 of 217"):
        register_blobs(np.zeros((3, 2)), LAYOUT)
