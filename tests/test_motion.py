"""A contact's velocity from a window of centroids (optitac_edge.core.motion): the mathematics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optitac_edge.core.motion import velocity_noise_factor, window_velocity

PERIOD = 1 / 240


def _line(v: tuple[float, float], n: int = 5, t0: float = 0.0, p0: tuple[float, float] = (1.0, -2.0)):
    t = t0 + PERIOD * np.arange(n)
    return t, np.asarray(p0) + np.outer(t - t0, v)


def test_a_straight_slide_gives_its_velocity_exactly_and_no_scatter() -> None:
    t, p = _line((10.0, -30.0))
    v, rms = window_velocity(t, p)
    np.testing.assert_allclose(v, (10.0, -30.0), rtol=1e-9)
    assert rms == pytest.approx(0.0, abs=1e-9)


def test_the_velocity_does_not_depend_on_the_clock_or_the_place() -> None:
    """Shifting every time, or every centroid, changes nothing (only differences count)."""
    t, p = _line((3.0, 4.0))
    rng = np.random.default_rng(0)
    p = p + rng.normal(0, 0.01, p.shape)
    v, rms = window_velocity(t, p)
    v2, rms2 = window_velocity(t + 12345.678, p + (7.0, -9.0))
    np.testing.assert_allclose(v2, v, rtol=1e-7)
    assert rms2 == pytest.approx(rms, rel=1e-7)


def test_rotating_the_centroids_rotates_the_velocity() -> None:
    t, p = _line((5.0, 1.0))
    p = p + np.random.default_rng(1).normal(0, 0.02, p.shape)
    a = math.radians(30)
    r = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    v, _ = window_velocity(t, p)
    vr, _ = window_velocity(t, p @ r.T)
    np.testing.assert_allclose(vr, r @ v, atol=1e-9)


def test_two_samples_are_the_finite_difference() -> None:
    v, rms = window_velocity(np.array([0.0, PERIOD]), np.array([[0.0, 0.0], [0.04, -0.01]]))
    np.testing.assert_allclose(v, (0.04 / PERIOD, -0.01 / PERIOD))
    assert math.isnan(rms)


def test_the_noise_of_the_velocity_is_the_centroids_noise_times_the_factor() -> None:
    """Many windows of a held contact with centroid noise sigma: the velocity's spread is sigma x factor, and
    the residual scatter estimates sigma."""
    rng = np.random.default_rng(2)
    sigma, w = 0.01, 5
    t = PERIOD * np.arange(w)
    vs, rmss = [], []
    for _ in range(4000):
        v, rms = window_velocity(t, rng.normal(0, sigma, (w, 2)))
        vs.append(v)
        rmss.append(rms)
    spread = np.std(np.asarray(vs), axis=0)
    want = sigma * velocity_noise_factor(w, PERIOD)
    np.testing.assert_allclose(spread, want, rtol=0.05)
    assert math.sqrt(np.mean(np.square(rmss))) == pytest.approx(sigma, rel=0.05)


def test_the_factor_for_a_window_of_five_frames_at_240_fps() -> None:
    """sum (k - 2)^2 = 10 for k = 0..4: 1 / (dt sqrt(10))."""
    assert velocity_noise_factor(5, PERIOD) == pytest.approx(240 / math.sqrt(10))


@pytest.mark.parametrize("t, p, why", [
    (np.zeros(3), np.zeros((3, 2)), "do not differ"),
    (np.zeros(1), np.zeros((1, 2)), "at least two"),
    (np.zeros(3), np.zeros((3, 3)), "centroids"),
])
def test_bad_windows_are_refused(t, p, why) -> None:
    with pytest.raises(ValueError, match=why):
        window_velocity(t, p)


@pytest.mark.parametrize("w, period", [(1, PERIOD), (5, 0.0), (5, math.inf), (5, math.nan)])
def test_bad_factors_are_refused(w, period) -> None:
    with pytest.raises(ValueError):
        velocity_noise_factor(w, period)
