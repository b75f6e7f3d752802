"""The switchable improvements beyond the paper (``ContactOptions``): hysteresis,
dead-fiber fill, several contacts, baseline tracking, bundle round trip."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from test_pipeline import LAYOUT, make_bundle, pressed_levels, render, rest_levels, warm

from optitac_edge.core.options import ContactOptions
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.errors import BundleError
from optitac_edge.io.bundle_file import load_bundle, save_bundle
from optitac_edge.io.contacts_csv import CONTACTS_HEADER, ContactsCsvWriter

PERIOD = 16_666_667  # 60 fps, ns
REST = np.full(LAYOUT.n_fibers, 200.0)
# levels far above the test frames' rounding noise: trunc 3 %, off 5 %, on 15 %
LEVELS = ContactOptions(noise_rel=0.0, floor_trunc=0.03, floor_off=0.05, floor_on=0.15)


def start(options: ContactOptions, dead: tuple[int, ...] = (), rest: np.ndarray = REST):
    bundle = make_bundle(dead=dead, options=options)
    pipe = Pipeline(bundle)
    for k, f in enumerate(warm(bundle, rest)):
        pipe.process_recorded(f, k * PERIOD)
    return bundle, pipe


def test_default_options_are_the_improvements_and_paper_switches_them_off() -> None:
    d, p = ContactOptions(), ContactOptions.paper()
    assert d.relative and d.noise_levels and d.hysteresis and d.fill_dead and d.track_baseline
    assert d.max_contacts == 4 and 0 < d.peak_fraction < 1
    assert p.is_paper and not d.is_paper
    assert not p.relative and p.max_contacts == 1 and p.peak_fraction == 0.0


def test_levels_from_measured_noise_with_floors() -> None:
    o = ContactOptions(noise_rel=0.002, k_trunc=4, k_off=6, k_on=10, floor_trunc=0.001,
                       floor_off=0.001, floor_on=0.03)
    _, pipe = start(o)
    trunc, off, on = pipe.levels.as_tuple()
    assert trunc == pytest.approx(0.008) and off == pytest.approx(0.012) and on == pytest.approx(0.03)
    _, pipe = start(dataclasses.replace(o, hysteresis=False))
    assert pipe.levels.as_tuple()[1] == pipe.levels.as_tuple()[2]


def test_hysteresis_marginal_press_neither_starts_nor_flickers() -> None:
    bundle, pipe = start(LEVELS)
    strong = render(bundle, pressed_levels(REST, 1.0, 0.5, depth=60.0))  # 30 % of the rest light
    marginal = render(bundle, pressed_levels(REST, 1.0, 0.5, depth=20.0))  # 10 %: between off and on
    rest = render(bundle, REST)
    seq = [marginal, marginal, strong, marginal, marginal, marginal, rest, marginal, rest]
    got = [pipe.process_recorded(f, (10 + k) * PERIOD).primary.contact for k, f in enumerate(seq)]
    assert got == [False, False, True, True, True, True, False, False, False]
    # without hysteresis the marginal press after the strong one is not a contact
    bundle, pipe = start(dataclasses.replace(LEVELS, hysteresis=False))
    got = [pipe.process_recorded(f, (10 + k) * PERIOD).primary.contact for k, f in enumerate(seq)]
    assert got == [False, False, True, False, False, False, False, False, False]


def test_dead_fiber_is_filled_from_its_neighbours() -> None:
    # the central fiber is dead and the press is right on it
    levels = pressed_levels(REST, 0.0, 0.0, depth=60.0)
    results = {}
    for fill in (False, True):
        bundle, pipe = start(dataclasses.replace(LEVELS, fill_dead=fill, peak_fraction=0.0), dead=(108,))
        e = pipe.process_recorded(render(bundle, levels), 10 * PERIOD).primary.copy()
        s = pipe.surface
        grid = bundle.grid
        col, row = int(np.argmin(np.abs(grid.x_mm))), int(np.argmin(np.abs(grid.y_mm)))
        ring = np.flatnonzero(np.isclose(np.hypot(*LAYOUT.xy_mm.T), 1.5, atol=0.01))
        ring_vals = [s[int(np.argmin(np.abs(grid.y_mm - LAYOUT.xy_mm[i, 1]))),
                      int(np.argmin(np.abs(grid.x_mm - LAYOUT.xy_mm[i, 0])))] for i in ring]
        results[fill] = (e, float(s[row, col]), float(np.mean(ring_vals)))
    e, centre, ring_mean = results[True]
    assert centre == pytest.approx(ring_mean, rel=0.05)  # no hole
    assert math.hypot(e.x_mm, e.y_mm) < 0.05
    _, centre_hole, ring_mean_hole = results[False]
    assert centre_hole < 0.2 * ring_mean_hole  # the paper's hole


def test_dead_fiber_going_dark_is_not_a_contact_with_fill() -> None:
    bundle, pipe = start(LEVELS, dead=(108, 109))
    dark = REST.copy()
    dark[[108, 109]] = 0.0
    result = pipe.process_recorded(render(bundle, dark), 10 * PERIOD)
    assert not result.primary.contact and result.n_contacts == 0


def test_two_presses_are_two_contacts_strongest_first() -> None:
    bundle, pipe = start(LEVELS)
    levels = pressed_levels(pressed_levels(REST, -5.0, 0.0, depth=60.0), 5.0, 2.0, depth=40.0)
    result = pipe.process_recorded(render(bundle, levels), 10 * PERIOD)
    e = result.primary
    assert e.contact and result.n_contacts == 2
    assert e is pipe.contacts[0]
    a, b = pipe.contacts[0], pipe.contacts[1]
    assert a.strength > b.strength and b.contact and list(result.touching()) == [a, b]
    assert math.hypot(a.x_mm + 5.0, a.y_mm) < 0.2
    assert math.hypot(b.x_mm - 5.0, b.y_mm - 2.0) < 0.2
    assert np.all(np.isfinite(a.hu)) and np.all(np.isfinite(b.hu))
    assert np.all(np.isfinite(a.features)) and np.all(np.isfinite(b.features))
    np.testing.assert_array_equal(b.features[:7], b.hu)
    # one contact only: the whole surface is one contact, between the presses
    bundle, pipe = start(dataclasses.replace(LEVELS, max_contacts=1))
    result = pipe.process_recorded(render(bundle, levels), 10 * PERIOD)
    assert result.n_contacts == 1 and -4.0 < result.primary.x_mm < 4.0
    # released: no contact
    bundle, pipe = start(LEVELS)
    pipe.process_recorded(render(bundle, levels), 10 * PERIOD)
    assert pipe.process_recorded(render(bundle, REST), 11 * PERIOD).n_contacts == 0


def test_peak_fraction_makes_widths_amplitude_invariant() -> None:
    widths = {}
    for frac in (0.0, 0.5):
        for depth in (40.0, 80.0):
            bundle, pipe = start(dataclasses.replace(LEVELS, peak_fraction=frac))
            e = pipe.process_recorded(render(bundle, pressed_levels(REST, 0.7, -0.3, depth, 2.2, 1.6, 20.0)), 10 * PERIOD).primary
            widths[frac, depth] = (e.major_mm, e.minor_mm)
    np.testing.assert_allclose(widths[0.5, 40.0], widths[0.5, 80.0], rtol=0.02)
    assert abs(widths[0.0, 40.0][0] / widths[0.0, 80.0][0] - 1) > 0.05


@pytest.mark.parametrize("shape_fraction", [0.0, 0.3, 0.6])
def test_shape_features_come_from_their_own_binarization_level(shape_fraction) -> None:
    from optitac_edge.core.moments import hu_moments, log_hu, q4_moment

    bundle, pipe = start(dataclasses.replace(LEVELS, peak_fraction=0.5, shape_fraction=shape_fraction))
    e = pipe.process_recorded(render(bundle, pressed_levels(REST, 0.7, -0.3, 60.0, 2.6, 1.4, 30.0)), 10 * PERIOD).primary
    assert e.contact
    surface = pipe.surface  # truncated at the noise level only; the moments' own cut is inside
    level = max(float(pipe.levels.as_tuple()[0]), (shape_fraction or 0.5) * float(surface.max()))
    mask = surface > level
    np.testing.assert_allclose(e.hu, log_hu(hu_moments(mask, bundle.grid)), rtol=1e-6, atol=1e-9)
    assert e.features[7] == pytest.approx(q4_moment(mask, bundle.grid), rel=1e-6, abs=1e-9)


def test_relative_signal_removes_transmission_spread() -> None:
    rest = rest_levels(3)
    bundle, pipe = start(LEVELS, rest=rest)
    levels = rest * (1.0 - 0.3 * np.exp(-0.5 * np.hypot(*(LAYOUT.xy_mm - (2.0, 1.0)).T) ** 2 / 2.0**2))
    e = pipe.process_recorded(render(bundle, levels), 10 * PERIOD).primary
    assert e.contact and math.hypot(e.x_mm - 2.0, e.y_mm - 1.0) < 0.15
    np.testing.assert_allclose(pipe.signal.max(), 0.3, atol=0.01)


def test_baseline_tracks_slow_led_drift_but_not_a_held_press() -> None:
    seconds = 20.0
    n = int(seconds * 60)

    def run(options: ContactOptions) -> int:
        bundle, pipe = start(options)
        false = 0
        for k in range(n):
            gain = 1.0 - 0.03 * k / n  # the LED dims by 3 % over 20 s
            false += pipe.process_recorded(render(bundle, REST * gain), (5 + k) * PERIOD).primary.contact
        return false

    tight = dataclasses.replace(LEVELS, floor_trunc=0.01, floor_off=0.015, floor_on=0.025,
                                compensate_gain=False)
    assert run(tight) == 0
    assert run(dataclasses.replace(tight, track_baseline=False)) > 100  # the test means something
    # the gain compensation alone also removes it
    assert run(dataclasses.replace(tight, track_baseline=False, compensate_gain=True)) == 0
    # a press held for 5 s is never absorbed, and released it is gone at once
    bundle, pipe = start(tight)
    pressed = render(bundle, pressed_levels(REST, -2.0, 3.0, depth=40.0))
    before = pipe.baseline.values.copy()
    strengths = []
    for k in range(300):
        e = pipe.process_recorded(pressed, (5 + k) * PERIOD).primary
        assert e.contact, k
        strengths.append(e.strength)
    assert strengths[-1] == pytest.approx(strengths[0], rel=1e-6)
    np.testing.assert_array_equal(pipe.baseline.values, before)
    assert not pipe.process_recorded(render(bundle, REST), 305 * PERIOD).primary.contact


def test_paper_options_override_gives_the_paper_pipeline() -> None:
    bundle = make_bundle(options=ContactOptions())
    paper = make_bundle()
    rest = rest_levels(5)
    frames = warm(bundle, rest) + [render(bundle, pressed_levels(rest, 1.5, -2.0, 50.0)), render(bundle, rest)]
    pa = Pipeline(bundle, ContactOptions.paper())
    a = [pa.process_recorded(f, k).primary.copy() for k, f in enumerate(frames)]
    pp = Pipeline(paper)
    b = [pp.process_recorded(f, k).primary.copy() for k, f in enumerate(frames)]
    for x, y in zip(a, b):
        assert x.to_dict() == y.to_dict()


def test_options_round_trip_through_the_bundle(tmp_path) -> None:
    opts = dataclasses.replace(ContactOptions(), peak_fraction=0.35, max_contacts=2, hysteresis=False,
                               noise_rel=0.0021, black_level=9.5)
    saved = save_bundle(make_bundle(options=opts), tmp_path / "cal.npz")
    loaded = load_bundle(tmp_path / "cal.npz")
    assert loaded.options == opts and saved.options == opts
    save_bundle(make_bundle(), tmp_path / "p.npz")
    assert load_bundle(tmp_path / "p.npz").options.is_paper


def _rewrite_meta(path, edit) -> None:
    from optitac_edge.io.bundle_file import _digest

    with np.load(path, allow_pickle=False) as npz:
        members = {k: npz[k] for k in npz.files}
    meta = json.loads(members.pop("meta").tobytes())
    members.pop("digest")
    edit(meta)
    meta_bytes = json.dumps(meta, sort_keys=True).encode()
    digest = _digest(meta_bytes, members)
    np.savez(path, **members, meta=np.frombuffer(meta_bytes, dtype=np.uint8),
             digest=np.frombuffer(digest.encode(), dtype=np.uint8))


def test_bundle_options_are_strictly_validated(tmp_path) -> None:
    path = tmp_path / "cal.npz"
    save_bundle(make_bundle(options=ContactOptions()), path)
    _rewrite_meta(path, lambda m: m["contact_options"].update(bogus_switch=True))
    with pytest.raises(BundleError, match="bogus_switch"):
        load_bundle(path)
    save_bundle(make_bundle(options=ContactOptions()), path)
    _rewrite_meta(path, lambda m: m["contact_options"].update(max_contacts=9))
    with pytest.raises(BundleError, match="max_contacts"):
        load_bundle(path)
    save_bundle(make_bundle(options=ContactOptions()), path)
    _rewrite_meta(path, lambda m: m["contact_options"].update(relative="yes"))
    with pytest.raises(BundleError, match="relative"):
        load_bundle(path)
    # a bundle from before the options existed is the paper's method
    save_bundle(make_bundle(options=ContactOptions()), path)
    _rewrite_meta(path, lambda m: m.pop("contact_options"))
    assert load_bundle(path).options.is_paper
    with pytest.raises(ValueError, match="peak_fraction"):
        ContactOptions(peak_fraction=1.5)


def test_contacts_csv_has_n_contacts_and_q4(tmp_path) -> None:
    bundle, pipe = start(LEVELS)
    out = tmp_path / "c.csv"
    levels = pressed_levels(pressed_levels(REST, -5.0, 0.0, depth=60.0), 5.0, 2.0, depth=40.0)
    with ContactsCsvWriter(out) as w:
        result = pipe.process_recorded(render(bundle, levels), 10 * PERIOD)
        q4 = float(result.primary.features[7])
        w.write(0, result)
        w.write(1, pipe.process_recorded(render(bundle, REST), 11 * PERIOD))
    rows = [r.split(",") for r in out.read_text().splitlines()]
    assert rows[0] == list(CONTACTS_HEADER)
    col = {name: k for k, name in enumerate(CONTACTS_HEADER)}
    assert rows[1][col["n_contacts"]] == "2" and rows[2][col["n_contacts"]] == "0"
    assert float(rows[1][col["q4"]]) == pytest.approx(q4, abs=1e-8) and rows[2][col["q4"]] == ""
    assert [int(r[col["t_ns"]]) for r in rows[1:]] == [10 * PERIOD, 11 * PERIOD]


def test_calibration_measures_noise_and_black_level() -> None:
    from optitac_edge import sim
    from optitac_edge.calibration import fibers as calibration

    sensor = sim.SimulatedSensor(seed=3)
    bundle = calibration.calibrate_fibers([sensor.frame() for _ in range(8)], "gray")
    o = bundle.options
    assert 0.0 < o.noise_rel < 0.02 and 0.0 < o.noise_gray < 3.0 and 0.0 < o.black_level < 40.0
    assert not o.is_paper


# -- common-mode LED gain compensation ----------------------------------------------------------

GAIN = dataclasses.replace(LEVELS, floor_trunc=0.01, floor_off=0.015, floor_on=0.025)


def big_press(rest: np.ndarray, depth: float = 0.5) -> np.ndarray:
    """A press darkening every fiber (>= 6 % at the rim, ``depth`` at the centre), like a 20 mm disc."""
    r = np.hypot(*LAYOUT.xy_mm.T)
    return rest * (1.0 - depth * (0.12 + 0.88 * np.clip(1.0 - r / 13.0, 0.0, 1.0) ** 1.5))


def test_gain_compensation_quick_presses_while_the_led_dims() -> None:
    """Press 2 frames, release 1 (no baseline tracking possible): the LED dims 3 % over 10 s."""
    n = 600
    results = {}
    for comp in (False, True):
        bundle, pipe = start(dataclasses.replace(GAIN, compensate_gain=comp, track_baseline=False))
        false = missed = 0
        for k in range(n):
            gain = 1.0 - 0.03 * k / n
            pressed = k % 3 != 2
            x = -6.0 + 12.0 * (k % 47) / 46.0
            levels = pressed_levels(REST, x, 1.0, depth=40.0) if pressed else REST
            e = pipe.process_recorded(render(bundle, levels * gain), (5 + k) * PERIOD).primary
            false += e.contact and not pressed
            missed += pressed and not e.contact
            if pressed and e.contact and comp:
                assert abs(e.x_mm - x) < 0.3
        results[comp] = false, missed
    assert results[False][0] > 50  # the problem exists without it
    assert results[True] == (0, 0)


def test_gain_compensation_does_not_eat_a_press_covering_the_whole_array() -> None:
    bundle, ref = start(dataclasses.replace(GAIN, compensate_gain=False))
    press = big_press(REST)
    expected = ref.process_recorded(render(bundle, press), 10 * PERIOD).primary.copy()
    assert expected.contact
    bundle, pipe = start(GAIN)
    e = pipe.process_recorded(render(bundle, press), 10 * PERIOD).primary
    assert e.contact and pipe.led_gain.gain == pytest.approx(1.0, abs=pipe.levels.as_tuple()[0])
    assert e.strength == pytest.approx(expected.strength, rel=0.03)
    assert e.major_mm == pytest.approx(expected.major_mm, rel=0.02)
    assert math.hypot(e.x_mm, e.y_mm) < 0.1
    # held for 2 s while the LED dims by 0.4 %: the gain limit grows with the rate, the press stays
    for k in range(120):
        gain = 1.0 - 0.004 * k / 120
        e = pipe.process_recorded(render(bundle, press * gain), (11 + k) * PERIOD).primary
        assert e.contact and math.hypot(e.x_mm, e.y_mm) < 0.1
    assert e.major_mm == pytest.approx(expected.major_mm, rel=0.03)
    # released: no contact, and the gain is measured again at once
    e = pipe.process_recorded(render(bundle, REST * 0.996), 200 * PERIOD).primary
    assert not e.contact and pipe.led_gain.gain == pytest.approx(0.996, abs=0.001)


def test_gain_compensation_measures_the_gain_beside_a_small_press() -> None:
    bundle, pipe = start(GAIN)
    pipe.process_recorded(render(bundle, REST * 0.995), 10 * PERIOD)  # contact-free: gain 0.995
    levels = pressed_levels(REST, 2.0, -1.0, depth=60.0) * 0.99
    e = pipe.process_recorded(render(bundle, levels), 70 * PERIOD).primary  # 1 s later: within 0.5 %
    assert e.contact and pipe.led_gain.gain == pytest.approx(0.99, abs=0.0005)
    assert math.hypot(e.x_mm - 2.0, e.y_mm + 1.0) < 0.15


def test_a_gain_step_as_a_whole_array_press_lifts_is_a_light_change_not_a_lingering_contact() -> None:
    """The LED drops 4 % at once (faster than gain_rate_per_s) in the frame a whole-array press
    lifts. Before issue 13.5 the gain was held at the press's and the step read as a contact for
    ~5 s, until the gain limit grew to it; now every fiber agrees on the new gain: no contact, one
    light change."""
    o = dataclasses.replace(GAIN, track_baseline=False)
    bundle, pipe = start(o)
    big = big_press(REST)  # a contact over the whole array, then the LED steps down as it lifts
    assert pipe.process_recorded(render(bundle, big), 10 * PERIOD).primary.contact
    dim = render(bundle, REST * 0.96)
    got = [pipe.process_recorded(dim, (11 + k) * PERIOD).primary.contact for k in range(int(10 / (PERIOD * 1e-9)))]
    assert not any(got)
    assert pipe.led_gain is not None and pipe.led_gain.light_changes == 1 and pipe.led_gain.gain == pytest.approx(0.96, abs=0.002)


def test_gain_compensation_off_in_the_paper_method() -> None:
    p = ContactOptions.paper()
    assert not p.compensate_gain and ContactOptions().compensate_gain
    assert "compensate_gain" in ContactOptions.SWITCHES
    with pytest.raises(ValueError, match="gain_rate_per_s"):
        ContactOptions(gain_rate_per_s=-1.0)


def test_a_light_change_is_reported_in_its_frame_only_not_again_while_a_tare_takes_the_baseline() -> None:
    """Bug: the flag was the gain compensation's last value, read by the loop after every frame, so the
    frames that took the baseline after a tare each reported the light change of the frame before it."""
    bundle, pipe = start(dataclasses.replace(GAIN, compensate_gain=True))
    pipe.process_recorded(render(bundle, REST), 5 * PERIOD)
    assert pipe.process_recorded(render(bundle, REST * 0.8), 6 * PERIOD).light_changed  # the LED dims by 20 %
    pipe.reset_baseline()  # a tare
    flags = [pipe.process_recorded(render(bundle, REST * 0.8), (7 + k) * PERIOD).light_changed
             for k in range(bundle.baseline_frames + 3)]
    assert flags == [False] * len(flags)
