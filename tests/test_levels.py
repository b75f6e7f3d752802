"""Contact levels from the data, per fiber (issue 37): each fiber's band from its own rest excursion, the typical
fiber's noise for the levels."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.core.layout import hex_layout
from optitac_edge.core.levels import NOISE_KEY, ContactLevels, banded, fiber_excess
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.sim.sensor import SimulatedSensor
from optitac_edge.sim.skin import Indenter

PERIOD = 16_666_667


def test_the_excess_is_each_fibers_excursion_beyond_the_typical_one() -> None:
    e = np.array([1.0, 1.0, 1.1, 0.9, 4.0, 2.0, 1.0, 9.0])
    live = np.ones(8, dtype=bool)
    live[-1] = False  # a dead fiber: no band, not in the median
    x = fiber_excess(e, live, samples=51)  # tol = 2 / sqrt(100) = 0.2
    assert x is not None and x.dtype == np.float32
    np.testing.assert_allclose(x, [0, 0, 0, 0, 4.0 - 1.2, 2.0 - 1.2, 0, 0], atol=1e-6)
    assert fiber_excess(np.ones(8), live, 51) is None  # nothing to do per frame
    assert fiber_excess(e, live, 1) is None  # one sample says nothing of a spread
    # fewer samples, a wider tolerance: 2 / sqrt(2 * 4) = 0.71
    np.testing.assert_allclose(fiber_excess(e, live, 5), np.maximum(e / 1.0 - 1 - 2 / math.sqrt(8), 0) * live,
                               atol=1e-6)


def _three_fibers(noise: list[float] | None, drift: list[float] | None, noise_is_drift: bool = False) -> ContactLevels:
    """Levels over three fibers of light 100 (on level 0.1, relative), 51 samples each (tol = 2 / sqrt(100))."""
    from types import SimpleNamespace

    from optitac_edge.core.options import ContactOptions

    options = ContactOptions(noise_levels=True, relative=True, on_level=0.1)
    fibers = SimpleNamespace(noise=None if noise is None else np.array(noise),
                             drift=None if drift is None else np.array(drift), baseline_frames=10, samples=51,
                             n_fibers=3, known=True, noise_is_drift=noise_is_drift)
    levels = ContactLevels(options, 10.0, fibers)  # type: ignore[arg-type]
    levels.update(np.array([100.0, 100.0, 100.0]), np.ones(3, dtype=bool))
    return levels


def _through(levels: ContactLevels, values: list[float]) -> np.ndarray:
    """The third fiber's signal through its band, for each of ``values`` (the others' at 0)."""
    assert levels.bands is not None
    out = []
    for v in values:
        s = np.array([0.0, 0.0, v], dtype=np.float32)
        out.append(banded(s, levels.bands, np.zeros(3, np.float32), np.zeros(3, np.float32))[2])
    return np.array(out)


def test_a_drifting_fibers_band_is_subtracted_from_every_value() -> None:
    """A fiber drifting 3 times as much as the others: its excess ``x = 3 - 1 - tol`` at the on level, ``on x``,
    comes off every value, a press's too (a drift rides on a press as on a rest frame: keeping a drifting
    fiber's press values read the real data set worse, core/levels.py); it reaches the on level at
    ``on (1 + x)``."""
    levels = _three_fibers(None, [0.01, 0.01, 0.03])
    x = 3 - 1 - 0.2
    assert levels.band is not None and levels.band[0] == levels.band[1] == 0
    assert float(levels.band[2]) == pytest.approx(0.1 * x, rel=1e-5)
    np.testing.assert_allclose(_through(levels, [0.05, 0.1 * (1 + x), 0.5, -0.5]),
                               [0.0, 0.1, 0.5 - 0.1 * x, -(0.5 - 0.1 * x)], rtol=1e-5, atol=1e-7)


def test_a_noisy_fibers_band_silences_its_noise_and_keeps_a_press() -> None:
    """A fiber 3 times as noisy (frame to frame) as the others reaches the on level at ``on (1 + x)`` too, but a
    press's values come through (less ``c^2 / s``, which falls as the press deepens): the simulator's dim
    fibers are noisy, not drifting, and subtracting their band read its widths ~10 % wider."""
    levels = _three_fibers([1.0, 1.0, 3.0], None)
    x = 3 - 1 - 0.2
    on = 0.1
    assert levels.band is not None and levels.band[2] == pytest.approx(on * math.sqrt(x * (1 + x)), rel=1e-5)
    low, at_on, deep = _through(levels, [on * math.sqrt(x * (1 + x)) * 0.99, on * (1 + x), 2.0])
    assert low == 0.0 and at_on == pytest.approx(on, rel=1e-5)
    assert deep == pytest.approx(2.0 - on * on * x * (1 + x) / 2.0, rel=1e-5)  # 0.025 below the value
    # the same excursion from drift comes off a press whole: 0.18 below the value
    drifting = _through(_three_fibers(None, [0.01, 0.01, 0.03]), [2.0])
    assert drifting[0] == pytest.approx(2.0 - on * x, rel=1e-5)


def test_noise_measured_between_snapshots_is_drift() -> None:
    """Snapshots far apart (a labelled data set): what ``calibrate fibers`` measured as noise is the fibers'
    drift between them, and is subtracted as a drift is."""
    noisy = _three_fibers([1.0, 1.0, 3.0], None)
    snapshots = _three_fibers([1.0, 1.0, 3.0], None, noise_is_drift=True)
    assert noisy.bands is not None and snapshots.bands is not None
    assert noisy.bands[1, 2] == 0.0 and noisy.bands[0, 2] > 0.0  # rows: c^2, shift
    assert snapshots.bands[0, 2] == 0.0 and snapshots.bands[1, 2] == pytest.approx(0.1 * 1.8, rel=1e-5)


def test_rest_frames_far_apart_are_flagged_as_snapshots(bundle_path) -> None:
    """``calibrate fibers`` counts only differences of rest frames within the gap as noise; with fewer than
    two of them, every difference is drift, and the bundle says so (``noise_between_snapshots``)."""
    from optitac_edge.calibration.fibers import measure_rest_noise
    from optitac_edge.io.bundle_file import load_bundle

    bundle = load_bundle(bundle_path)
    sensor = SimulatedSensor(layout=bundle.layout, seed=5)
    frames = np.stack([sensor.frame_from_darkening(sensor.darkening(())) for _ in range(6)])
    mean = frames.astype(np.float64).mean(axis=0)
    mean = mean if mean.ndim == 2 else mean.mean(axis=2)
    close = np.arange(6, dtype=np.int64) * 16_666_667
    video = measure_rest_noise(frames, bundle.fibers, mean, times_ns=close, gap_ns=500_000_000)
    apart = measure_rest_noise(frames, bundle.fibers, mean, times_ns=close * 1000, gap_ns=500_000_000)
    one_gap = measure_rest_noise(frames, bundle.fibers, mean, times_ns=np.array([0, 1, 2, 3, 4, 9]) * 10 ** 9,
                                 gap_ns=1_500_000_000)
    assert not video.between_snapshots and video.samples == 5
    assert apart.between_snapshots and apart.samples == 5
    assert not one_gap.between_snapshots and one_gap.samples == 4  # the far frame's difference left out
    with pytest.raises(ValueError, match="5 times for 6 rest frames"):
        measure_rest_noise(frames, bundle.fibers, mean, times_ns=close[:5], gap_ns=500_000_000)


def _ring_jitter(sensor: SimulatedSensor, ring: np.ndarray, presses: list[Indenter | None], sigma: float,
                 seed: int) -> list[np.ndarray]:
    """Frames whose ``ring`` fibers' light jitters by ``sigma`` (relative) from frame to frame."""
    rng = np.random.default_rng(seed)
    out = []
    for p in presses:
        d = sensor.darkening(() if p is None else (p,))
        d[ring] += rng.normal(0.0, sigma, ring.size)
        out.append(sensor.frame_from_darkening(d))
    return out


@pytest.mark.parametrize("compiled", [False, True])
def test_a_noisy_outer_ring_gets_bands_of_its_own_and_raises_no_level(compiled) -> None:
    """A 61-fiber array whose outer ring (24 fibers) jitters by 3 % from frame to frame, four times as much as
    the others: the levels come from the typical fiber (the 95th percentile over the surface took them from the
    ring), the ring's fibers get bands, no rest frame makes a contact, and a press in the middle is found.
    Without the bands the ring's jitter is a contact in most frames."""
    layout = hex_layout(4, 4.0)
    sensor = SimulatedSensor(layout=layout, seed=3)
    ring = np.flatnonzero(np.hypot(*layout.xy_mm.T) > 3.6 * 4.0 * 0.95)
    assert ring.size == 24
    rest = _ring_jitter(sensor, ring, [None] * 40, 0.03, seed=1)
    bundle = calibrate_fibers(rest, "gray", layout=layout)
    noise = bundle.extra_arrays[NOISE_KEY]
    inner = np.setdiff1d(np.arange(61), ring)
    assert np.median(noise[ring]) > 4 * np.median(noise[inner])
    assert bundle.options.noise_rel < 2 * np.median(noise[inner])  # the typical fiber's, not the ring's
    press = Indenter("circle", 0.0, 0.0, size_mm=10.0, depth_mm=0.6)
    frames = rest[:10] + _ring_jitter(sensor, ring, [None] * 150 + [press] * 10, 0.03, seed=2)
    for with_bands in (True, False):
        b = bundle if with_bands else bundle.with_updates(extra_arrays={})
        pipe = Pipeline(b, compiled=compiled)
        contacts = [pipe.process_recorded(f, k * PERIOD).n_contacts for k, f in enumerate(frames)]
        false = sum(n > 0 for n in contacts[10:160])
        if with_bands:
            assert pipe.levels.band is not None and np.count_nonzero(pipe.levels.band[ring]) >= 20
            assert np.count_nonzero(pipe.levels.band[inner]) <= 2
            assert false == 0 and all(n == 1 for n in contacts[160:]), (false, contacts[160:])
        else:
            assert false > 75


def test_the_level_sits_in_the_middle_of_the_widest_gap_of_least_error() -> None:
    from optitac_edge.calibration.levels_fit import choose_level

    # apart: the geometric middle of the highest rest and the lowest contact statistic
    assert choose_level(np.array([0.01, 0.02, 0.04]), np.array([0.16, 0.3])) == pytest.approx(0.08)
    # overlapping: one rest frame above two contacts; the least balanced error (1/4 + 0) is between them
    level = choose_level(np.array([0.01, 0.02, 0.03, 0.2]), np.array([0.05, 0.1, 0.3]))
    assert level == pytest.approx(math.sqrt(0.03 * 0.05))
    # below the floor counts as the floor; empty sides are refused
    assert choose_level(np.array([-0.5, 0.0]), np.array([0.004])) == pytest.approx(math.sqrt(0.001 * 0.004))
    with pytest.raises(ValueError, match="rest frames and contact frames"):
        choose_level(np.array([]), np.array([0.1]))


def test_held_out_levels_never_see_the_frames_they_are_scored_on() -> None:
    """Statistics of rest frames (runs of 3) and presses (3 frames each) that never overlap: every fold's
    level lies between them and the held-out rates are perfect; a fiber of every rest frame 10 times noisier
    than the others gets a band, so it does not decide the level."""
    from optitac_edge.calibration.levels_fit import held_out_levels, rest_runs

    rng = np.random.default_rng(0)
    n_fibers, rest_frames, presses = 30, 60, 20
    signals = rng.normal(0.0, 0.01, (rest_frames + 3 * presses, n_fibers))
    signals[:, 7] *= 10  # a noisy fiber: at rest it reaches 0.2 and more
    for p in range(presses):  # none on the noisy fiber
        fiber = p % (n_fibers - 1)
        signals[rest_frames + 3 * p:rest_frames + 3 * p + 3, fiber + (fiber >= 7)] += 0.5
    contact = np.arange(signals.shape[0]) >= rest_frames
    frames = np.arange(signals.shape[0])
    frames[:rest_frames] += frames[:rest_frames] // 3  # runs of three consecutive frames
    runs = rest_runs(contact, np.zeros(contact.size, dtype=np.int64), frames, frames * 16_666_667, 500_000_000)
    assert runs.min() == -20 and np.all(runs[rest_frames:] == 0)
    groups = np.where(contact, (np.arange(signals.shape[0]) - rest_frames) // 3, runs)
    held = held_out_levels(signals, None, contact, groups, np.ones(n_fibers, dtype=bool))
    assert held.folds == 8 and held.detection == 1.0 and held.false_rate == 0.0
    assert all(0.05 < level < 0.5 for level in held.levels)


def test_calibrate_levels_chooses_on_the_recordings_and_evaluate_reports_it(tmp_path, bundle_path, capsys) -> None:
    """On simulated presses: a level between the rest frames' statistics and the presses', each fiber's rest
    excursion kept, held-out rates in the bundle, and evaluate saying the level and its rates."""
    import shutil

    from optitac_edge.cli import main
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.sim.scenarios import write_scenario

    seen = write_scenario(tmp_path / "seen", "seen", seed=3, frames=200)
    cal = tmp_path / "cal.npz"
    shutil.copy(bundle_path, cal)
    assert main(["calibrate", "levels", str(seen), "--cal", str(cal)]) == 0
    out = capsys.readouterr().out
    assert "heldout detection 1" in out and "heldout false contacts 0" in out
    bundle = load_bundle(cal)
    meta = bundle.extra_meta["levels"]
    assert bundle.options.on_level == pytest.approx(meta["on_level"], abs=1e-5)
    assert bundle.options.on_level > 5 * bundle.options.noise_rel
    assert bundle.extra_arrays["levels/fiber_drift"].shape == (217,) and meta["drift_samples"] > 40
    assert main(["evaluate", str(seen), "--cal", str(cal)]) == 0
    out = capsys.readouterr().out
    assert f"levels: on {meta['on_level']:.4f}" in out and "held out at calibration: detection 100.0 %" in out
