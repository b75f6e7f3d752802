"""The fibers' vibration (optitac_edge.core.vibration): the filter's mathematics and the event's behaviour."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal as sps

from optitac_edge.core import compiled
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


class _Meter:
    """A meter and the signal buffer it reads: the numpy one, or the kernel's (the same interface)."""

    def __init__(self, kind: str, live: np.ndarray | None = None) -> None:
        self.signal = np.zeros(N, dtype=np.float32)
        live = np.ones(N, dtype=bool) if live is None else live
        self.m = VibrationMeter(self.signal, live) if kind == "numpy" else compiled.compiled_vibration(self.signal,
                                                                                                       live)

    def run(self, frames: np.ndarray, trunc: float = TRUNC) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        levels, on, began = [], [], []
        for f in frames:
            self.signal[:] = f
            levels.append(self.m.update(trunc, DT_NS))
            on.append(self.m.vibrating)
            began.append(self.m.began)
        return np.array(levels), np.array(on), np.array(began)


KINDS = ["numpy", pytest.param("kernel", marks=pytest.mark.skipif(not compiled.kernel_status()[0],
                                                                  reason="the compiled kernel is not built"))]


@pytest.fixture(params=KINDS)
def kind(request) -> str:
    return request.param


def test_the_meters_filter_is_the_high_pass_fiber_by_fiber() -> None:
    """Against scipy's lfilter of the same signal, started at rest on the first frame."""
    meter = _Meter("numpy")
    x = _frames(300, 1) + np.linspace(0, 0.5, N, dtype=np.float32)
    meter.run(x, trunc=10.0)
    b, a = butter2_highpass(20.0, FPS)
    ref = sps.lfilter(b, a, x[1:] - x[1], axis=0)  # the first frame designs the filter and is its rest
    h = meter.m._h  # the last frame's output, its mean across fibers taken out
    np.testing.assert_allclose(h, ref[-1] - ref[-1].mean(), atol=2e-6)


def test_the_kernels_meter_is_the_numpy_one() -> None:
    """Every frame's level and flags, over a touch, quiet holds, a shake and a release."""
    if not compiled.kernel_status()[0]:
        pytest.skip("the compiled kernel is not built")
    live = np.ones(N, dtype=bool)
    live[[3, 50, 120]] = False
    frames = np.concatenate([_frames(300, 20), _frames(600, 21, contact=slice(80, 130)), _frames(300, 22)])
    t = np.arange(300) / FPS
    frames[600:900, 80:130] += (4 * SIGMA * np.sin(2 * np.pi * 45.0 * t))[:, None].astype(np.float32)
    ref, kern = _Meter("numpy", live), _Meter("kernel", live)
    a, b = ref.run(frames), kern.run(frames)
    np.testing.assert_allclose(a[0], b[0], rtol=1e-4, equal_nan=True)
    assert (a[1] == b[1]).all() and (a[2] == b[2]).all() and a[1].any()
    ref.m.reset()
    kern.m.reset()
    a, b = ref.run(frames[:100]), kern.run(frames[:100])
    np.testing.assert_allclose(a[0], b[0], rtol=1e-4, equal_nan=True)


def test_quiet_fibers_read_about_one_and_never_vibrate(kind: str) -> None:
    """A minute of noise at 240 fps, contact-free then pressed: the level is the noise's (1) and no event."""
    levels, on, _ = _Meter(kind).run(_frames(7200, 2))
    assert np.isnan(levels[:LEARN_FRAMES]).all() and not on.any()
    assert np.median(levels[100:]) == pytest.approx(1.0, abs=0.05)
    frames = _frames(7200, 3, contact=slice(80, 130))
    # a fresh meter (a tare) during a press: the press is the rest the filter starts from
    levels, on, _ = _Meter(kind).run(frames)
    assert not on.any() and np.median(levels[100:]) == pytest.approx(1.0, abs=0.1)


def test_a_press_growing_steadily_and_a_dimming_led_do_not_vibrate(kind: str) -> None:
    """A ramp of the pressed fibers' signal (the filter's double zero at DC) and a common change of light."""
    meter = _Meter(kind)
    meter.run(_frames(240, 4))
    frames = _frames(2400, 5, contact=slice(80, 130))
    t = np.arange(2400)[:, None] / FPS
    frames[:, 80:130] += (0.2 * t).astype(np.float32)  # +0.2 signal per second
    # every fiber: the LEDs breathe and step (below the truncation level: a larger change is a contact, or is
    # taken out by the gain compensation before the signal)
    frames += (0.004 * np.sin(2 * np.pi * 0.5 * t)).astype(np.float32)
    frames[1200:] += 0.003
    _, on, _ = meter.run(frames)
    assert on[:WINDOW].all() and not on[240:].any()  # the touch itself vibrates, briefly


@pytest.mark.parametrize("hz", [30.0, 60.0, 100.0])
def test_a_shake_of_the_pressed_fibers_raises_the_event_within_five_frames(hz: float, kind: str) -> None:
    """The pressed fibers' signal oscillates by 3 noise sigmas (a 0.05 mm shake in the simulator moves
    the fibers at a contact's edge by more)."""
    meter = _Meter(kind)
    meter.run(_frames(240, 6))
    frames = _frames(960, 7, contact=slice(80, 130))
    t = np.arange(960)[480:] / FPS
    frames[480:, 80:130] += (3 * SIGMA * np.sin(2 * np.pi * hz * t))[:, None].astype(np.float32)
    _levels, on, began = meter.run(frames)
    assert on[0] and not on[240:480].any()  # the touch, then a quiet hold
    first = 240 + int(np.argmax(on[240:]))
    assert 480 <= first <= 480 + 5 and began[first] and began[240:].sum() == 1


def test_a_reset_learns_the_noise_again(kind: str) -> None:
    meter = _Meter(kind)
    meter.run(_frames(60, 8))
    meter.m.reset()
    levels, _, _ = meter.run(1.5 * _frames(60, 9))
    assert np.isnan(levels[:LEARN_FRAMES]).all() and np.median(levels[30:]) == pytest.approx(1.0, abs=0.15)


def test_dead_fibers_are_left_out(kind: str) -> None:
    live = np.ones(N, dtype=bool)
    live[:10] = False
    meter = _Meter(kind, live)
    frames = _frames(600, 10)
    frames[:, :10] = np.random.default_rng(11).normal(0, 1.0, (600, 10))  # a dead fiber's garbage
    levels, on, _ = meter.run(frames)
    assert not on.any() and np.median(levels[100:]) == pytest.approx(1.0, abs=0.05)


def test_the_filter_is_designed_for_the_cameras_nominal_rate_not_a_bunched_first_interval(kind: str) -> None:
    """Issue 38 item 14: the filter was designed from the first frame interval; frames handed over 1 µs apart
    made it a filter for 1 MHz. With the nominal period it is the 240 fps filter whatever the intervals; at
    rest, frames bunched and spread at random vibrate nothing."""
    ref, meter = _Meter("numpy"), _Meter(kind)
    ref.m.period_s = meter.m.period_s = 1.0 / FPS
    frames = _frames(2400, 9)
    dts = np.random.default_rng(9).choice([1_000, DT_NS, 3 * DT_NS], size=len(frames))
    dts[:2] = 1_000  # the first intervals bunched: what the filter was designed from
    got, ref_levels = [], []
    for f, dt in zip(frames, dts):
        ref.signal[:] = meter.signal[:] = f
        ref_levels.append(ref.m.update(TRUNC, int(dt)))
        got.append((meter.m.update(TRUNC, int(dt)), meter.m.vibrating))
    b, a = butter2_highpass(20.0, FPS)
    assert ref.m._coef == pytest.approx((b[0], b[1], a[1], a[2], b[2]))
    levels = np.array([g[0] for g in got])
    assert not any(g[1] for g in got) and np.median(levels[100:]) == pytest.approx(1.0, abs=0.05)
    np.testing.assert_allclose(levels, ref_levels, rtol=1e-4, equal_nan=True)  # the kernel's is the numpy one
