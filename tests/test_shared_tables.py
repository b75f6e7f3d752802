"""Read-only tables shared by the pipelines that have the same ones (issue 41: six patches of one design kept six
copies of one surface operator, together more than a Raspberry Pi 4's L2)."""

from __future__ import annotations

import gc

import numpy as np
import pytest

from optitac_edge.core import shared_tables as st
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.io.bundle_file import load_bundle
from optitac_edge.sim.camera import SimCamera


def test_equal_tables_are_one_read_only_copy_and_different_ones_are_not():
    a = np.arange(12, dtype=np.float32)
    first = st.shared_table(a)
    assert first is not a and not first.flags.writeable and a.flags.writeable  # the caller's array as it was
    assert st.shared_table(a.copy()) is first
    assert st.shared_table(a.astype(np.float64)) is not first  # another dtype
    assert st.shared_table(a.reshape(3, 4)) is not first  # another shape
    b = a.copy()
    b[5] = np.nextafter(b[5], np.float32(100))  # one bit
    assert st.shared_table(b) is not first
    strided = np.arange(24, dtype=np.float32)[::2]
    assert st.shared_table(strided).flags.c_contiguous
    with pytest.raises(ValueError, match="read-only"):
        first[0] = 1.0
    key = next(k for k, v in st._TABLES.items() if v is first)
    del first
    gc.collect()
    assert key not in st._TABLES  # it went with its last user


def test_two_compiled_pipelines_of_one_design_read_one_surface_operator_and_give_the_same(bundle_path):
    one, two = (Pipeline(load_bundle(bundle_path), compiled=True) for _ in range(2))
    if not one.compiled:
        pytest.skip("the kernel is not built here")
    tables = {k: v for k, v in one.engine.plan.surface_op.items() if isinstance(v, np.ndarray)}
    assert {"gs_col_env", "gs_coef", "tri_cols", "tri_weights"} <= set(tables)
    assert all(two.engine.plan.surface_op[k] is v for k, v in tables.items())
    cam = SimCamera(fps=240, seed=5, rest_frames=12, realtime=False)
    touching = 0
    try:
        for k in range(120):
            frame = cam.read().frame  # type: ignore[union-attr]
            a, b = one.process(frame, k * 4_166_667), two.process(frame, k * 4_166_667)
            assert repr(a) == repr(b)
            touching += a.n_contacts > 0
    finally:
        cam.close()
    assert touching > 10
