"""Tests of session drift ("days") and sensor variants of the simulator."""

from __future__ import annotations

import hashlib
from dataclasses import replace

import numpy as np
import pytest

from optitac_edge.core.layout import hex_layout
from optitac_edge.io.recording import Recording
from optitac_edge.sim.drift import MAX_REST_LEVEL, SessionDrift, sensor_variant, variant_sensor_seed
from optitac_edge.sim.optics import CameraOptics
from optitac_edge.sim.scenarios import DRIFT_GAP, DRIFT_HOLD, DRIFT_WARMUP, FPS, REST_FRAMES, write_scenario
from optitac_edge.sim.sensor import SimulatedSensor
from optitac_edge.sim.skin import Indenter, SkinModel, fiber_darkening

LAYOUT = hex_layout()
PRESS = Indenter("circle", 1.0, -0.5, 0.0, 5.0, 3.0)
SMALL = CameraOptics(width=160, height=120)


def _centroids(frame: np.ndarray, centres: np.ndarray, radius: float, bg: float) -> np.ndarray:
    """Intensity-weighted centroid (col, row) of the pixels within ``radius`` of each centre."""
    gray = frame.astype(np.float64) - bg
    out = np.empty_like(centres)
    r = int(np.ceil(radius)) + 1
    dy, dx = np.mgrid[-r : r + 1, -r : r + 1]
    for i, (c, rw) in enumerate(centres):
        cols, rows = round(c) + dx, round(rw) + dy
        w = gray[rows, cols] * ((cols - c) ** 2 + (rows - rw) ** 2 <= radius**2)
        out[i] = (w * cols).sum() / w.sum(), (w * rows).sum() / w.sum()
    return out


def _fiber_means(frame: np.ndarray, centres: np.ndarray, radius: float = 4.0) -> np.ndarray:
    rows, cols = np.indices(frame.shape[:2])
    return np.array(
        [frame[(cols - c) ** 2 + (rows - r) ** 2 <= radius**2].mean() for c, r in centres]
    )


def _sha(frame: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(frame).tobytes()).hexdigest()


def test_day_zero_is_nominal_and_renders_as_before(tmp_path) -> None:
    assert SessionDrift.for_day(0) == SessionDrift() and SessionDrift().is_nominal
    a, b = SimulatedSensor(seed=3), SimulatedSensor(seed=3, drift=SessionDrift.for_day(0))
    ind = [Indenter("square", 2, 1, 20, 6, 2.5)]
    rest, pressed = a.frame(), a.frame(ind)
    assert np.array_equal(rest, b.frame()) and np.array_equal(pressed, b.frame(ind))
    # bit-identical to the simulator before drift existed (frames recorded then)
    assert _sha(rest) == "8a11609602e075f17410ba32caa741a3856ba0b6"
    assert _sha(pressed) == "0631e43f4abb43a380e41fdcf84f53166166f808"
    # write_scenario's defaults are day 0, variant 0
    plain = Recording(write_scenario(tmp_path / "a", "shapes", seed=4, frames=40, optics=SMALL))
    dayed = Recording(
        write_scenario(tmp_path / "b", "shapes", seed=4, frames=40, optics=SMALL, day=0, variant=0)
    )
    assert np.array_equal(np.asarray(plain.frames), np.asarray(dayed.frames))


def test_camera_shift_moves_the_faces_exactly() -> None:
    quiet = CameraOptics(noise_sigma=0.0, row_noise_sigma=0.0)
    a = SimulatedSensor(optics=quiet)
    b = SimulatedSensor(optics=quiet, drift=SessionDrift(camera_shift_px=(0.3, -0.2)))
    assert np.allclose(b.fiber_centres_px - a.fiber_centres_px, (0.3, -0.2))
    centres = a.fiber_centres_px
    radius = 0.85 * LAYOUT.pitch_mm * a.renderer.projection.scale / 2 + 3  # whole blurred face
    moved = _centroids(b.frame(), centres, radius, 10) - _centroids(a.frame(), centres, radius, 10)
    assert np.abs(moved - (0.3, -0.2)).max() < 0.03, np.abs(moved - (0.3, -0.2)).max()


def test_led_gain_scales_rest_brightness() -> None:
    quiet = CameraOptics(noise_sigma=0.0, row_noise_sigma=0.0)
    a = SimulatedSensor(optics=quiet)
    b = SimulatedSensor(optics=quiet, drift=SessionDrift(led_gain=1.04))
    ma, mb = (_fiber_means(s.frame(), a.fiber_centres_px) - 10 for s in (a, b))
    ratio = mb / ma
    assert abs(np.median(ratio) - 1.04) < 0.004 and np.abs(ratio - 1.04).max() < 0.01


def test_pin_gain_scales_darkening() -> None:
    plain = fiber_darkening(LAYOUT.xy_mm, [PRESS])
    sensor = SimulatedSensor(drift=SessionDrift(pin_gain=0.95))
    assert np.allclose(sensor.darkening([PRESS]), 0.95 * plain)
    quiet = CameraOptics(noise_sigma=0.0, row_noise_sigma=0.0)
    a, b = (
        SimulatedSensor(optics=quiet),
        SimulatedSensor(optics=quiet, drift=SessionDrift(pin_gain=1.05)),
    )
    centre = int(np.argmax(plain))
    drops = [
        1
        - (_fiber_means(s.frame([PRESS]), a.fiber_centres_px)[centre] - 10)
        / (_fiber_means(s.frame(), a.fiber_centres_px)[centre] - 10)
        for s in (a, b)
    ]
    assert abs(drops[1] / drops[0] - 1.05) < 0.01


def test_depth_jitter_per_press_and_seed() -> None:
    drift = SessionDrift(depth_jitter=0.04)
    s1, s1b, s2 = (SimulatedSensor(seed=k, drift=drift) for k in (1, 1, 2))
    d1, d1b, d2 = (s.darkening([PRESS]) for s in (s1, s1b, s2))
    assert np.array_equal(d1, d1b)  # reproducible
    assert not np.allclose(d1, d2)  # the seed changes the real depth
    depths = []
    for s in (s1, s2):
        real = s.last_real_indenters[0].depth_mm
        depths.append(real)
        assert real != 3.0 and abs(real / 3.0 - 1) <= 2.5 * 0.04
        assert np.array_equal(s.darkening([PRESS]), s.darkening([PRESS]))  # same press, same depth
        assert s.last_real_indenters[0].depth_mm == real
    # a new press (after a contact-free frame) draws a new depth
    s1.darkening([])
    s1.darkening([PRESS])
    assert s1.last_real_indenters[0].depth_mm != depths[0]


def test_depth_jitter_statistics() -> None:
    s = SimulatedSensor(seed=7, drift=SessionDrift(depth_jitter=0.04))
    rel = []
    for _ in range(400):
        rel.append(s.real_indenters([PRESS])[0].depth_mm / 3.0 - 1.0)
        s.real_indenters([])
    assert abs(np.std(rel) - 0.04) < 0.006 and abs(np.mean(rel)) < 0.008


def test_truth_keeps_commanded_depth_meta_has_drift(tmp_path) -> None:
    out = write_scenario(tmp_path / "r", "repeat", seed=1, frames=40, optics=SMALL, day=3)
    rec = Recording(out)
    sim = rec.meta.extra["simulator"]
    assert sim["day"] == 3 and sim["drift"] == SessionDrift.for_day(3).to_dict()
    held = rec.truth.contact
    assert np.all(rec.truth.depth_mm[held] == 3.0)
    real = np.array(sim["real_depth_mm"])
    assert (
        len(real) == 10 and np.all(real[:, 1] != 3.0) and np.all(np.abs(real[:, 1] / 3 - 1) < 0.15)
    )
    nominal = Recording(write_scenario(tmp_path / "n", "repeat", seed=1, frames=40, optics=SMALL))
    shift = np.array(sim["fiber_centres_px"]) - np.array(
        nominal.meta.extra["simulator"]["fiber_centres_px"]
    )
    assert np.allclose(shift, SessionDrift.for_day(3).camera_shift_px, atol=2e-4)


def test_days_are_reproducible_distinct_and_in_range() -> None:
    days = [SessionDrift.for_day(d) for d in range(1, 21)]
    assert SessionDrift.for_day(5) == days[4] and len(set(days)) == 20
    assert SessionDrift.for_day(5, sensor_seed=1) != days[4]
    for d in days:
        assert all(0.15 <= abs(v) <= 0.5 for v in d.camera_shift_px)
        assert 0.02 <= abs(d.led_gain - 1) <= 0.05 and 0.02 <= abs(d.pin_gain - 1) <= 0.05
        assert 0.03 <= d.depth_jitter <= 0.05 and 0.0005 <= abs(d.led_drift_per_s) <= 0.0015
    assert SessionDrift.for_day(2, led_drift=False).led_drift_per_s == 0
    with pytest.raises(ValueError):
        SessionDrift(led_gain=0)
    with pytest.raises(ValueError):
        SessionDrift.for_day(-1)


def test_within_recording_led_drift() -> None:
    quiet = CameraOptics(noise_sigma=0.0, row_noise_sigma=0.0)
    s = SimulatedSensor(optics=quiet, drift=SessionDrift(led_drift_per_s=0.002), fps=60.0)
    first = _fiber_means(s.frame(), s.fiber_centres_px) - 10  # t = 0
    late = _fiber_means(s.frame(t_s=10.0), s.fiber_centres_px) - 10
    assert abs(np.median(late / first) - 1.02) < 0.003
    assert s.frame_index == 2
    # per-fiber drift: fibers drift apart, reproducibly
    d = SessionDrift(fiber_drift_per_s=0.001)
    a, b = SimulatedSensor(optics=quiet, drift=d), SimulatedSensor(optics=quiet, drift=d)
    ratio = (_fiber_means(a.frame(t_s=10.0), a.fiber_centres_px) - 10) / first
    assert 0.005 < np.std(ratio) < 0.02
    assert np.array_equal(a.brightness(10.0), b.brightness(10.0))


def test_drift_scenario_brightens_and_presses_sometimes(tmp_path) -> None:
    n = 300
    rec = Recording(write_scenario(tmp_path / "d", "drift", seed=2, frames=n, optics=SMALL, day=1))
    truth = rec.truth
    assert len(rec) == n and not truth.contact[: REST_FRAMES + DRIFT_GAP].any()
    first_press = REST_FRAMES + DRIFT_GAP
    assert truth.contact[first_press : first_press + DRIFT_HOLD].all()
    assert 0.15 < truth.contact.mean() < 0.3 and not truth.contact[-1]
    sim = rec.meta.extra["simulator"]
    assert np.isclose(sim["drift"]["led_drift_per_s"] * (n - 1) / FPS, DRIFT_WARMUP)
    assert (
        sim["drift"]["led_gain"] == SessionDrift.for_day(1).led_gain
    )  # the day's other drift stays
    centres = np.array(sim["fiber_centres_px"])
    bg = sim["optics"]["background_gray"]
    early = np.mean([_fiber_means(rec.frame(i), centres, 2.0) for i in range(5)], axis=0) - bg
    late = np.mean([_fiber_means(rec.frame(i), centres, 2.0) for i in range(n - 5, n)], axis=0) - bg
    expected = (1 + DRIFT_WARMUP * (n - 3) / (n - 1)) / (1 + DRIFT_WARMUP * 2 / (n - 1))
    assert abs(np.median(late / early) - expected) < 0.006, np.median(late / early)
    assert 0.003 < np.std(late / early) < 0.02  # plus per-fiber drift and noise


def test_drift_scenario_can_dim(tmp_path) -> None:
    n = 120
    out = write_scenario(tmp_path / "d", "drift", frames=n, optics=SMALL, warmup=-0.03)
    rec = Recording(out)
    sim = rec.meta.extra["simulator"]
    assert np.isclose(sim["drift"]["led_drift_per_s"] * (n - 1) / FPS, -0.03)
    centres = np.array(sim["fiber_centres_px"])
    first, last = (_fiber_means(rec.frame(i), centres, 2.0) - 10 for i in (0, n - 1))
    assert abs(np.median(last / first) - 0.97) < 0.01


@pytest.mark.parametrize(("width", "height"), [(640, 480), (160, 120)])
def test_variants_differ_fit_and_do_not_saturate(width: int, height: int) -> None:
    assert sensor_variant(0) == ({}, SkinModel()) and variant_sensor_seed(0) != variant_sensor_seed(
        1
    )
    assert sensor_variant(4, width, height) == sensor_variant(4, width, height)
    bright = SessionDrift(led_gain=1.05, camera_shift_px=(0.5, -0.5))
    seen = []
    for v in range(1, 9):
        overrides, skin = sensor_variant(v, width, height)
        seen.append((overrides, skin))
        optics = replace(CameraOptics(width=width, height=height), **overrides)
        assert 0.6 * 0.85 <= optics.fill_fraction <= 0.9 and abs(optics.k1) <= 0.03
        assert 0.7 <= optics.blur_sigma_px <= 1.5 and 1 <= optics.noise_sigma <= 3
        assert 0.05 <= optics.transmission_sigma <= 0.12 and 0 <= optics.vignetting <= 0.25
        assert 0.6 < skin.max_darkening < 0.95
        sensor = SimulatedSensor(
            optics=optics, skin=skin, sensor_seed=variant_sensor_seed(v), drift=bright
        )
        assert optics.background_gray + sensor.rest_peak.max() <= MAX_REST_LEVEL + 1e-6
        frame = sensor.frame()
        assert frame.max() < 255
        c = sensor.fiber_centres_px
        margin = LAYOUT.pitch_mm / 3 * sensor.renderer.projection.scale
        assert np.all(c.min(axis=0) > margin) and np.all(
            c.max(axis=0) < (width - margin, height - margin)
        )
        # a central press still darkens clearly, far fibers are untouched
        d = sensor.darkening([Indenter("circle", 0, 0, 0, 5, 3)])
        assert 0.25 < d.max() < 0.8 and d[np.linalg.norm(LAYOUT.xy_mm, axis=1) > 8].max() < 0.05
    rotations = [o["rotation_deg"] for o, _ in seen]
    assert len(set(rotations)) == len(rotations) and np.ptp(rotations) > 90
    assert len({o["mirror"] for o, _ in seen}) == 2
    assert len({s.compression_gain for _, s in seen}) == len(seen)


def test_write_scenario_variant(tmp_path) -> None:
    out = write_scenario(
        tmp_path / "v", "shapes", seed=1, frames=25, optics=SMALL, variant=2, day=1
    )
    rec = Recording(out)
    sim = rec.meta.extra["simulator"]
    overrides, skin = sensor_variant(2, 160, 120)
    assert sim["variant"] == 2 and sim["sensor_seed"] == variant_sensor_seed(2)
    assert (
        sim["optics"]["rotation_deg"] == overrides["rotation_deg"] and sim["skin"] == skin.to_dict()
    )
    assert (
        sim["optics"]["width"] == 160
        and sim["drift"] == SessionDrift.for_day(1, variant_sensor_seed(2)).to_dict()
    )
    again = Recording(
        write_scenario(tmp_path / "w", "shapes", seed=1, frames=25, optics=SMALL, variant=2, day=1)
    )
    assert np.array_equal(np.asarray(rec.frames), np.asarray(again.frames))
    other = Recording(
        write_scenario(tmp_path / "x", "shapes", seed=1, frames=25, optics=SMALL, variant=3, day=1)
    )
    assert not np.array_equal(np.asarray(rec.frames), np.asarray(other.frames))
    # the same seed gives the same presses on every sensor and day
    assert np.array_equal(rec.truth.x_mm, other.truth.x_mm, equal_nan=True)


def test_rgb_with_drift() -> None:
    drift = SessionDrift.for_day(2)
    sensor = SimulatedSensor(optics=CameraOptics(rgb=True, width=320, height=240), drift=drift)
    frame = sensor.frame([PRESS])
    assert frame.shape == (240, 320, 3) and frame.dtype == np.uint8
    assert np.allclose(
        sensor.fiber_centres_px
        - SimulatedSensor(optics=CameraOptics(rgb=True, width=320, height=240)).fiber_centres_px,
        drift.camera_shift_px,
    )
