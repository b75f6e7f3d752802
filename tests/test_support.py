"""Neighbour support (issue 37): a fiber's signal counts only as far as its second-strongest neighbour's."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from optitac_edge.core.layout import hex_layout
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.core.support import NeighbourSupport, neighbour_table, supported
from optitac_edge.io.bundle_file import load_bundle
from optitac_edge.sim.sensor import SimulatedSensor
from optitac_edge.sim.skin import Indenter


def test_a_lone_fiber_is_cut_to_its_neighbours_and_a_patch_keeps_its_rim() -> None:
    layout = hex_layout(3, 1.0)
    table = neighbour_table(layout)
    centre = int(np.argmin(np.hypot(*layout.xy_mm.T)))
    ring = np.flatnonzero(np.isclose(np.hypot(*(layout.xy_mm - layout.xy_mm[centre]).T), 1.0))
    assert sorted(table[centre]) == sorted(ring)
    corner = int(np.argmax(np.hypot(*layout.xy_mm.T)))
    assert np.count_nonzero(table[corner] >= 0) == 3 and np.all(table[corner][3:] == -1)
    support = NeighbourSupport(table)
    lone = np.zeros(layout.n_fibers, dtype=np.float32)
    lone[centre] = 0.5
    assert support.peak(lone) == 0.0 and np.all(support.limited(lone) == 0)
    patch = np.zeros(layout.n_fibers, dtype=np.float32)
    patch[centre], patch[ring] = 0.5, 0.3
    limited = support.limited(patch)
    assert limited[centre] == pytest.approx(0.3)  # the peak: its second neighbour's
    assert np.all(limited[ring] == pytest.approx(0.3))  # the rim: borne out by the centre and a ring neighbour
    assert support.peak(patch) == pytest.approx(0.3) and patch[centre] == 0.5  # the signal is left as it is
    rng = np.random.default_rng(0)
    rows = rng.normal(0, 0.1, (20, layout.n_fibers)).astype(np.float32)
    np.testing.assert_allclose(supported(rows, table), [support.limited(r).copy() for r in rows], atol=1e-7)


@pytest.mark.parametrize("compiled", [False, True])
def test_a_fiber_that_darkens_alone_makes_no_contact_with_support(bundle_path, compiled) -> None:
    """One fiber 40 % darker than its baseline (it drifted, a real skin's do): a contact without support, none
    with it; a press is found either way."""
    bundle = load_bundle(bundle_path)
    sensor = SimulatedSensor(seed=2)
    rest = [sensor.frame() for _ in range(10)]
    dark = np.zeros(217)
    dark[100] = 0.4
    drifted = [sensor.frame_from_darkening(dark) for _ in range(5)]
    press = [sensor.frame((Indenter("circle", 3.0, 2.0, size_mm=5.0, depth_mm=2.0),)) for _ in range(5)]
    for support in (False, True):
        pipe = Pipeline(bundle.with_updates(options=dataclasses.replace(bundle.options, support=support)),
                        compiled=compiled)
        n = [pipe.process_recorded(f, k * 16_666_667).n_contacts for k, f in enumerate(rest + drifted + press)]
        assert (sum(n[10:15]) == 0) == support, n
        assert all(c >= 1 for c in n[15:])
