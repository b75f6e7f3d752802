"""Orientation: the layout's symmetries, and a fiber map off by one of them found from presses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.calibration.orientation import (
    Symmetry,
    fit_orientation,
    is_verified,
    layout_symmetries,
    reorient_bundle,
)
from optitac_edge.calibration.steps import calibrate_centroid, calibrate_orientation
from optitac_edge.cli import main
from optitac_edge.core.layout import FiberLayout, hex_layout
from optitac_edge.core.levels import DRIFT_KEY, NOISE_KEY
from optitac_edge.io.bundle_file import load_bundle, save_bundle
from optitac_edge.io.recording import Recording
from optitac_edge.sim.scenarios import write_scenario


def test_the_default_hexagon_has_twelve_symmetries_identity_first() -> None:
    layout = hex_layout()
    sym = layout_symmetries(layout)
    assert len(sym) == 12 and sym[0].is_identity
    assert sorted((h.mirror, round(h.rotation_deg)) for h in sym) == sorted(
        (m, 60 * k) for m in (False, True) for k in range(6))
    for h in sym:  # each is a bijection that maps every fiber onto a fiber
        assert np.array_equal(np.sort(h.permutation), np.arange(layout.n_fibers))
        assert np.allclose(h.apply(layout.xy_mm), layout.xy_mm[h.permutation], atol=1e-9)


def test_a_custom_layout_has_only_its_own_symmetries() -> None:
    hexagon = hex_layout(rings=3)
    xy = hexagon.xy_mm
    off_axis = int(np.argmin(np.hypot(xy[:, 0] - 2.5 * 1.5, xy[:, 1] - 1.5 * math.sqrt(3) / 2)))
    keep = np.arange(len(xy)) != off_axis  # one fiber missing off every mirror axis: nothing but the identity
    lone = layout_symmetries(FiberLayout(ids=hexagon.ids[keep], xy_mm=xy[keep]))
    assert len(lone) == 1 and lone[0].is_identity
    grid = np.array([(x, y) for x in (-3.0, -1.5, 0.0, 1.5, 3.0) for y in (-1.5, 0.0, 1.5)])  # a 5x3 rectangle
    rect = layout_symmetries(FiberLayout(ids=np.arange(15), xy_mm=grid))
    assert sorted((h.mirror, round(h.rotation_deg)) for h in rect) == [(False, 0), (False, 180), (True, 0),
                                                                     (True, 180)]


@pytest.mark.parametrize("k", range(12))
def test_fit_finds_the_symmetry_presses_were_read_through(k) -> None:
    sym = layout_symmetries(hex_layout())
    rng = np.random.default_rng(k)
    true = rng.uniform(-9, 9, (20, 2))
    measured = sym[k].apply(true) + rng.normal(0, 0.3, true.shape)
    fit = fit_orientation(measured, true, sym, 1.5)
    assert fit.symmetry is sym[k] and fit.best_rmse_mm < 0.6


@pytest.mark.parametrize("true, why", [
    (np.zeros((5, 2)) + 0.05, "cannot tell"),  # on the centre: every symmetry fits
    (np.array([[4.0, 0.0], [8.0, 0.0], [-6.0, 0.0]]), "cannot tell"),  # along a mirror axis only
])
def test_presses_that_cannot_tell_are_refused(true, why) -> None:
    sym = layout_symmetries(hex_layout())
    fit = fit_orientation(true.copy(), true, sym, 1.5)
    assert fit.symmetry is None and why in fit.reason


def test_no_symmetry_fits_presses_read_elsewhere() -> None:
    sym = layout_symmetries(hex_layout())
    true = np.array([[5.0, 1.0], [-3.0, 6.0], [2.0, -7.0]])
    fit = fit_orientation(true + 6.0, true, sym, 1.5)
    assert fit.symmetry is None and "no orientation fits" in fit.reason


@pytest.fixture(scope="module")
def presses(tmp_path_factory):
    path = write_scenario(tmp_path_factory.mktemp("orient") / "unseen", "unseen", seed=4, frames=400)
    rec = Recording(path)
    return rec, calibrate_fibers(rec.rest_frames(), rec.pixel_format)  # the simulator is unrotated, unmirrored


@pytest.mark.parametrize("mirror", (False, True))
@pytest.mark.parametrize("k", range(6))
def test_every_wrong_orientation_hint_is_corrected_from_presses(presses, k, mirror) -> None:
    """Each of the 12 symmetries given as the hint, 20 degrees off (either way, by turns): the right fiber map.
    (tools/orientation_sweep.py runs all 36: each symmetry exactly and 20 degrees off both ways.)"""
    offset = 20 if (k + mirror) % 2 else -20
    rec, right = presses
    wrong = calibrate_fibers(rec.rest_frames(), rec.pixel_format, rotation_hint_deg=60 * k + offset, mirror=mirror)
    fixed, fit = calibrate_orientation(rec, wrong)
    assert fit.symmetry is not None and fit.symmetry.is_identity == (k == 0 and not mirror)
    assert is_verified(fixed) and not fixed.transform.mirror
    assert min(fixed.transform.rotation_deg, 360 - fixed.transform.rotation_deg) < 0.5
    assert np.array_equal(fixed.fibers.pixel_start, right.fibers.pixel_start)
    assert np.array_equal(fixed.fibers.pixel_index, right.fibers.pixel_index)
    assert np.allclose(fixed.transform.layout_to_image(fixed.layout.xy_mm), fixed.fibers.centroid_px, atol=1.0)


def test_reorienting_drops_the_models_fitted_through_the_wrong_map(presses) -> None:
    rec, right = presses
    bundle, _ = calibrate_centroid(rec, right)
    assert "centroid_map" in str(sorted(bundle.extra_meta)) or bundle.extra_arrays
    h = layout_symmetries(bundle.layout)[3]
    turned = reorient_bundle(bundle, h, "test")
    assert not any(k.startswith(("centroid", "report/")) for k in turned.extra_arrays)
    assert "centroid_fit" not in turned.extra_meta and turned.extra_meta["orientation"]["corrected"] == h.label


def test_calibrate_centroid_refuses_a_wrong_orientation_and_says_how_to_fix_it(presses, tmp_path, capsys) -> None:
    rec, _ = presses
    cal = tmp_path / "cal.npz"
    save_bundle(calibrate_fibers(rec.rest_frames(), rec.pixel_format, rotation_hint_deg=60.0), cal)
    before = cal.read_bytes()
    assert main(["calibrate", "centroid", str(rec.path), "--cal", str(cal)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "rotated 300°" in err
    assert f"calibrate orientation {rec.path} --cal {cal}" in err
    assert cal.read_bytes() == before
    assert main(["calibrate", "orientation", str(rec.path), "--cal", str(cal)]) == 0
    assert "its fiber map was rotated 300°" in capsys.readouterr().out
    assert main(["calibrate", "centroid", str(rec.path), "--cal", str(cal)]) == 0
    assert is_verified(load_bundle(cal))


def test_calibrate_orientation_refuses_presses_that_cannot_tell(tmp_path, capsys) -> None:
    from optitac_edge.io.recording import RecordingMeta
    from optitac_edge.io.recording_writer import Press, RecordingWriter
    from optitac_edge.sim.sensor import SimulatedSensor
    from optitac_edge.sim.skin import Indenter

    sensor = SimulatedSensor(seed=0)
    press = Indenter(shape="circle", x_mm=0.0, y_mm=0.0, angle_deg=0.0, size_mm=5.0, depth_mm=3.0)
    rec_path = tmp_path / "centre"
    with RecordingWriter(rec_path, 30, sensor.frame_shape, RecordingMeta(rest_frames=10, fps=60.0),
                         with_truth=True) as w:
        for i in range(30):
            pressed = i >= 20
            w.write(i, sensor.frame((press,) if pressed else ()))
            w.write_truth(i, Press("circle", 0.0, 0.0, 0.0, 5.0, 3.0) if pressed else None)
    rec = Recording(rec_path)
    cal = tmp_path / "cal.npz"
    save_bundle(calibrate_fibers(rec.rest_frames(), rec.pixel_format), cal)
    before = cal.read_bytes()
    assert main(["calibrate", "orientation", str(rec_path), "--cal", str(cal)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "cannot tell" in err and "press away from the centre" in err
    assert main(["calibrate", "centroid", str(rec_path), "--cal", str(cal)]) == 2
    assert "cannot confirm the bundle's orientation" in capsys.readouterr().err
    assert cal.read_bytes() == before


def test_symmetry_labels() -> None:
    ident = Symmetry(0.0, False, np.arange(3))
    assert ident.label == "as it is" and ident.is_identity
    assert Symmetry(120.0, True, np.arange(3)).label == "rotated 120°, mirrored"


def _fiducial_layout(tmp_path, marks: dict[int, str]):
    from optitac_edge.io.layout_csv import load_layout_csv

    layout = hex_layout()
    path = tmp_path / "layout.csv"
    lines = ["fiber,x_mm,y_mm,fiducial"] + [
        f"{int(i)},{x:.6f},{y:.6f},{marks.get(k, '')}" for k, (i, (x, y)) in enumerate(zip(layout.ids, layout.xy_mm))]
    path.write_text("\n".join(lines) + "\n")
    return path, load_layout_csv(path)


def _fiber_at(x: float, y: float) -> int:
    xy = hex_layout().xy_mm
    return int(np.argmin(np.hypot(xy[:, 0] - x, xy[:, 1] - y)))


@pytest.mark.parametrize("k, mirror", [(0, False), (2, False), (1, True), (5, True)])
def test_dark_fiducials_settle_the_orientation_from_rest_frames(tmp_path, k, mirror) -> None:
    from optitac_edge.sim.optics import CameraOptics
    from optitac_edge.sim.sensor import SimulatedSensor

    dark = (_fiber_at(3.75, 1.3), _fiber_at(-6.0, 5.2))  # off every mirror axis of the hexagon
    sensor = SimulatedSensor(optics=CameraOptics(dark_fibers=dark), seed=1)
    rest = np.stack([sensor.frame(()) for _ in range(8)])
    _, layout = _fiducial_layout(tmp_path, {i: "dark" for i in dark})
    right = calibrate_fibers(rest, "gray", layout=layout)
    bundle = calibrate_fibers(rest, "gray", layout=layout, rotation_hint_deg=60 * k + 10, mirror=mirror)
    assert is_verified(bundle) and np.array_equal(bundle.fibers.dead, right.fibers.dead)
    assert set(np.flatnonzero(bundle.fibers.dead)) == set(dark)
    assert np.array_equal(bundle.fibers.pixel_index, right.fibers.pixel_index) and not bundle.transform.mirror


def test_symmetric_fiducials_are_refused_in_one_line(tmp_path, capsys) -> None:
    rec = write_scenario(tmp_path / "rest", "rest", seed=0)
    path, _ = _fiducial_layout(tmp_path, {_fiber_at(0.0, 0.0): "dark"})  # the centre: as symmetric as the layout
    assert main(["calibrate", "fibers", str(rec), "-o", str(tmp_path / "c.npz"), "--layout", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "fiducials cannot tell" in err and not (tmp_path / "c.npz").exists()


def test_a_bad_fiducial_cell_is_refused(tmp_path) -> None:
    from optitac_edge.errors import ConfigError
    from optitac_edge.io.layout_csv import load_layout_csv

    path, _ = _fiducial_layout(tmp_path, {3: "dark"})
    path.write_text(path.read_text().replace(",dark", ",grey"))
    with pytest.raises(ConfigError, match="line 5: fiducial must be 'dark', 'bright' or empty"):
        load_layout_csv(path)


def test_the_gates_are_in_pitches_of_the_array() -> None:
    """A 61-fiber array at 4 mm pitch whose presses read through it mirrored fit to 3 mm RMS (0.75 pitch):
    accepted, where the absolute 2 mm gate refused a real sensor's presses at 3.05 mm; read 6 mm off (1.5
    pitch) they are refused, and the line says what to check."""
    layout = hex_layout(4, 4.0)
    sym = layout_symmetries(layout)
    mirrored = next(h for h in sym if h.mirror and h.rotation_deg == 0)
    rng = np.random.default_rng(3)
    true = rng.uniform(-12, 12, (30, 2))
    noise = rng.normal(0, 1.0, true.shape)
    noise *= 3.0 / np.sqrt(np.mean(np.sum(noise ** 2, axis=1)))  # exactly 3 mm RMS
    fit = fit_orientation(mirrored.apply(true) + noise, true, sym, layout.pitch_mm)
    assert fit.symmetry is mirrored and abs(fit.best_rmse_mm - 3.0) < 1e-9
    off = fit_orientation(mirrored.apply(true) + 2 * noise, true, sym, layout.pitch_mm)
    assert off.symmetry is None and "1.50 pitch, accepted below 1.33 pitch" in off.reason
    assert "sensor frame" in off.reason and "layout" in off.reason


def test_many_noisy_presses_decide_by_their_evidence() -> None:
    """17 presses read 4.2 mm RMS off through a mirrored 4 mm array (a real sensor's), the next symmetry 7 mm:
    a ratio under 2 that the gate refused, evidence of 10^7 to one that decides; two such presses do not."""
    layout = hex_layout(4, 4.0)
    sym = layout_symmetries(layout)
    mirrored = next(h for h in sym if h.mirror and h.rotation_deg == 0)
    rng = np.random.default_rng(8)
    true = rng.uniform(-11, 11, (17, 2))
    noise = rng.normal(0, 1.0, true.shape)
    noise *= 4.2 / np.sqrt(np.mean(np.sum(noise ** 2, axis=1)))
    fit = fit_orientation(mirrored.apply(true) + noise, true, sym, layout.pitch_mm)
    second = sorted(fit.rmse_mm)[1]
    assert fit.symmetry is mirrored and second < 2 * fit.best_rmse_mm
    few = fit_orientation(mirrored.apply(true[:2]) + noise[:2], true[:2], sym, layout.pitch_mm)
    assert few.symmetry is None


def test_reorienting_carries_each_fibers_noise_and_drift_with_its_pixels(presses) -> None:
    """The per-fiber levels (calibrate fibers' noise, calibrate levels' drift) belong to the fiber whose
    pixels they were measured on: when those pixels move to another fiber id, so do they (a stale array
    put a noisy fiber's wide band on a quiet one and left the noisy one bare: false contacts)."""
    _, right = presses
    n = right.layout.n_fibers
    noise, drift = np.arange(n, dtype=np.float32) + 1.0, np.arange(n, dtype=np.float32) / n
    bundle = right.with_updates(extra_arrays={NOISE_KEY: noise, DRIFT_KEY: drift})
    h = layout_symmetries(bundle.layout)[7]
    turned = reorient_bundle(bundle, h, "test")
    moved = turned.fibers.centroid_px
    for i in (0, 5, n - 1):  # fiber i now holds the pixels (and so the light) that were fiber p[i]'s
        j = int(h.permutation[i])
        assert np.allclose(moved[i], right.fibers.centroid_px[j])
        assert turned.extra_arrays[NOISE_KEY][i] == noise[j] and turned.extra_arrays[DRIFT_KEY][i] == drift[j]
