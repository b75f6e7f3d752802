"""The fibers' vibration (optitac_edge.core.vibration): the filter's mathematics and the event's behaviour."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal as sps

from optitac_edge.core.vibration import (
    LEARN_FRAMES,
    WINDOW,
    VibrationMeter,
    butter2_highpass,
)

FPS = 240.0
DT_NS = round(1e9 / FPS)
N = 217
SIGMA = 0.002  # the fibers' noise, signal units
TRUNC = 0.01


@pytest.mark.parametrize(("cutoff", "rate"), [(20.0, 240.0), (20.0, 120.0), (9.0, 30.0), (1.0, 1000.0)])
def test_the_high_pass_is_scipys_butterworth(cutoff: float, rate: float) -> None:
    b, a = butter2_highpass(cutoff, rate)
    b_ref, a_ref = sps.butter(2, cutoff / (rate / 2), "high")
    np.testing.assert_allclose(b, b_ref, rtol=1e-12)
    np.testing.assert_allclose(a, a_ref, rtol=1e-12)


@pytest.mark.parametrize("cutoff", [0.0, 120.0, math.nan])
def test_a_cut_off_outside_the_band_is_refused(cutoff: float) -> None:
    with pytest.raises(ValueError, match="cut-off"):
        butter2_highpass(cutoff, 240.0)


def _frames(n: int, seed: int, contact: slice | None = None) -> np.ndarray:
    """``n`` frames of fiber noise; the fibers of ``contact`` pressed (signal 0.3)."""
    s = np.random.default_rng(seed).normal(0.0, SIGMA, (n, N)).astype(np.float32)
    if contact is not None:
        s[:, contact] += 0.3
    return s


def _run(meter: VibrationMeter, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    levels, on, began = [], [], []
    for f in frames:
        levels.append(meter.update(f, TRUNC, DT_NS))
        on.append(meter.vibrating)
        began.append(meter.began)
    return np.array(levels), np.array(on), np.array(began)


def test_the_meters_filter_is_the_high_pass_fiber_by_fiber() -> None:
    """Against scipy's lfilter of the same signal, started at rest on the first frame."""
    meter = VibrationMeter(np.ones(N, dtype=bool))
    x = _frames(300, 1) + np.linspace(0, 0.5, N, dtype=np.float32)
    for f in x:
        meter.update(f, 10.0, DT_NS)
    b, a = butter2_highpass(20.0, FPS)
    zi = sps.lfilter_zi(b, a)[:, None] * 0  # rest for the first frame: a constant input gives nothing
    ref, _ = sps.lfilter(b, a, x[1:] - x[1], axis=0, zi=zi)  # the first frame designs the filter
    np.testing.assert_allclose(meter._h + meter._h.mean() * 0, ref[-1] - ref[-1].mean(), atol=2e-6)


def test_quiet_fibers_read_about_one_and_never_vibrate() -> None:
    """A minute of noise at 240 fps, contact-free then pressed: the level is the noise's (1) and no event."""
    meter = VibrationMeter(np.ones(N, dtype=bool))
    levels, on, _ = _run(meter, _frames(7200, 2))
    assert np.isnan(levels[:LEARN_FRAMES]).all() and not on.any()
    assert np.median(levels[100:]) == pytest.approx(1.0, abs=0.05)
    frames = _frames(7200, 3, contact=slice(80, 130))
    # a fresh meter (a tare) during a press: the press is the rest the filter starts from
    levels, on, _ = _run(VibrationMeter(np.ones(N, dtype=bool)), frames)
    assert not on.any() and np.median(levels[100:]) == pytest.approx(1.0, abs=0.1)


def test_a_press_growing_steadily_and_a_dimming_led_do_not_vibrate() -> None:
    """A ramp of the pressed fibers' signal (the filter's double zero at DC) and a common change of light."""
    meter = VibrationMeter(np.ones(N, dtype=bool))
    _run(meter, _frames(240, 4))
    frames = _frames(2400, 5, contact=slice(80, 130))
    t = np.arange(2400)[:, None] / FPS
    frames[:, 80:130] += (0.2 * t).astype(np.float32)  # +0.2 signal per second
    # every fiber: the LEDs breathe and step (below the truncation level: a larger change is a contact, or is
    # taken out by the gain compensation before the signal)
    frames += (0.004 * np.sin(2 * np.pi * 0.5 * t)).astype(np.float32)
    frames[1200:] += 0.003
    _, on, _ = _run(meter, frames)
    assert on[:WINDOW].all() and not on[240:].any()  # the touch itself vibrates, briefly


@pytest.mark.parametrize("hz", [30.0, 60.0, 100.0])
def test_a_shake_of_the_pressed_fibers_raises_the_event_within_five_frames(hz: float) -> None:
    """The pressed fibers' signal oscillates by 3 noise sigmas (a 0.05 mm shake in the simulator moves
    the fibers at a contact's edge by more)."""
    meter = VibrationMeter(np.ones(N, dtype=bool))
    _run(meter, _frames(240, 6))
    frames = _frames(960, 7, contact=slice(80, 130))
    t = np.arange(960)[480:] / FPS
    frames[480:, 80:130] += (3 * SIGMA * np.sin(2 * np.pi * hz * t))[:, None].astype(np.float32)
    _levels, on, began = _run(meter, frames)
    assert on[0] and not on[240:480].any()  # the touch, then a quiet hold
    first = 240 + int(np.argmax(on[240:]))
    assert 480 <= first <= 480 + 5 and began[first] and began[240:].sum() == 1


def test_a_reset_learns_the_noise_again() -> None:
    meter = VibrationMeter(np.ones(N, dtype=bool))
    _run(meter, _frames(60, 8))
    meter.reset()
    levels, _, _ = _run(meter, 1.5 * _frames(60, 9))
    assert np.isnan(levels[:LEARN_FRAMES]).all() and np.median(levels[30:]) == pytest.approx(1.0, abs=0.15)


def test_dead_fibers_are_left_out() -> None:
    live = np.ones(N, dtype=bool)
    live[:10] = False
    meter = VibrationMeter(live)
    frames = _frames(600, 10)
    frames[:, :10] = np.random.default_rng(11).normal(0, 1.0, (600, 10))  # a dead fiber's garbage
    levels, on, _ = _run(meter, frames)
    assert not on.any() and np.median(levels[100:]) == pytest.approx(1.0, abs=0.05)
