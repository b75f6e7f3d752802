import numpy as np
import pytest

from optitac_edge.core.layout import hex_layout
from optitac_edge.errors import ConfigError
from optitac_edge.io.layout_csv import load_layout_csv, save_layout_csv


def test_default_layout_is_217_fiber_hexagon():
    layout = hex_layout()
    assert layout.n_fibers == 217
    assert layout.pitch_mm == pytest.approx(1.5)
    # the central fiber is at the origin, the corners of the hexagon 8 pitches out
    assert np.linalg.norm(layout.xy_mm, axis=1).min() == 0.0
    assert layout.radius_mm == pytest.approx(12.0)
    # every interior fiber has six neighbours at exactly one pitch
    counts = np.array([len(n) for n in layout.neighbours()])
    assert counts.max() == 6 and np.sum(counts == 6) == 217 - 6 * 8
    # rows parallel to x: 17 distinct y values, the middle row has 17 fibers
    ys = np.round(layout.xy_mm[:, 1], 9)
    assert len(np.unique(ys)) == 17 and np.sum(ys == 0) == 17


def test_fiber_numbering_is_row_major_from_top():
    xy = hex_layout().xy_mm
    assert xy[0, 1] == xy[:, 1].max() and xy[0, 0] < xy[1, 0]
    assert np.all(np.diff(xy[:, 1]) <= 1e-9)
    assert tuple(xy[108]) == (0.0, 0.0)


def test_layout_csv_round_trip(tmp_path):
    layout = hex_layout(rings=3, pitch_mm=2.0)
    save_layout_csv(layout, tmp_path / "l.csv")
    back = load_layout_csv(tmp_path / "l.csv")
    np.testing.assert_array_equal(back.ids, layout.ids)
    np.testing.assert_allclose(back.xy_mm, layout.xy_mm, atol=1e-6)


@pytest.mark.parametrize(
    "text, message",
    [
        ("a,b,c\n1,2,3\n", "header"),
        ("fiber,x_mm,y_mm\n1,2\n", "expected 3 cells"),
        ("fiber,x_mm,y_mm\n1,2,zz\n", "not a number"),
        ("fiber,x_mm,y_mm\n" + "1,0,0\n" * 8, "duplicate"),
        ("fiber,x_mm,y_mm\n1,0,0\n2,1,0\n", "at least 7"),
        # a layout x 1e300 or x 1e-300 ended in a traceback deep in the fiber map
        ("fiber,x_mm,y_mm\n" + "".join(f"{i},{x * 1e300},{y * 1e300}\n" for i, (x, y) in
                                      enumerate(hex_layout().xy_mm)), "within 1000 mm of the centre"),
        ("fiber,x_mm,y_mm\n" + "".join(f"{i},{x * 1e-300},{y * 1e-300}\n" for i, (x, y) in
                                      enumerate(hex_layout().xy_mm)), "at least 0.01 mm apart"),
    ],
)
def test_bad_layout_csv_names_file_and_problem(tmp_path, text, message):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message) as info:
        load_layout_csv(path)
    assert str(path) in str(info.value)


def test_missing_layout_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_layout_csv(tmp_path / "nope.csv")


def test_the_calibrated_mesh_and_the_smallest_contact_follow_the_pitch() -> None:
    """The mesh has the paper's 6.2 cells a pitch (100 x 100 over its 217 fibers at 1.5 mm, as before) and the
    smallest contact its 0.44 square pitches (1 mm2 there), for any pitch; a large array keeps at most 100 a
    side (its matrix grows with cells x fibers)."""
    from optitac_edge.core.grid import SurfaceGrid
    from optitac_edge.core.options import ContactThresholds

    for rings, pitch, side in ((8, 1.5, 100), (4, 4.0, 51), (4, 1.0, 51), (2, 1.5, 26), (18, 1.5, 100)):
        layout = hex_layout(rings, pitch)
        grid = SurfaceGrid.for_layout(layout)
        assert grid.n == side, (rings, pitch)
        if side < 100:
            assert abs(pitch / grid.step_mm - 99 / 16) < 0.1
        assert ContactThresholds.for_pitch(layout.pitch_mm).min_area_mm2 == pytest.approx(pitch ** 2 / 2.25)
    assert SurfaceGrid.for_layout(hex_layout()) == SurfaceGrid.over_layout(hex_layout())
