"""A contact's velocity from a window of centroids (optitac_edge.core.motion): the mathematics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optitac_edge.core import compiled
from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.motion import (
    MIN_SLIP_SPEED_MM_S,
    WINDOW,
    ContactMotion,
    velocity_noise_factor,
    window_velocity,
)

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


# -- ContactMotion: a tracked contact's velocity and slip state, frame by frame -------------------------------

PERIOD_NS = round(PERIOD * 1e9)
BUILT = compiled.kernel_status()[0]


@pytest.fixture(params=["python", pytest.param("kernel", marks=pytest.mark.skipif(not BUILT, reason="not built"))])
def motion(request):
    """A fresh ContactMotion, or the kernel's (the same interface)."""
    return ContactMotion() if request.param == "python" else compiled.compiled_motion()


def _feed(motion: ContactMotion, xy: np.ndarray, *, cid: int = 7, t_ns: np.ndarray | None = None,
          first_frame: int = 0) -> list[ContactEstimate]:
    """One contact with id ``cid`` at the centroids ``xy`` (F, 2), a frame each; the estimates it got."""
    out = []
    for k, (x, y) in enumerate(xy):
        c = ContactEstimate(contact=True, x_mm=float(x), y_mm=float(y), contact_id=cid, touch_frame=first_frame)
        frame = first_frame + k
        motion.update([c], 1, frame, int(t_ns[k]) if t_ns is not None else frame * PERIOD_NS)
        out.append(c)
    return out


def _held(n: int, sigma: float, seed: int = 0, at: tuple[float, float] = (2.0, -1.0)) -> np.ndarray:
    return np.asarray(at) + np.random.default_rng(seed).normal(0.0, sigma, (n, 2))


def test_the_tracked_velocity_is_the_window_fit(motion) -> None:
    xy = _held(40, 0.01, seed=3) + np.outer(np.arange(40) * PERIOD, (12.0, -5.0))
    got = _feed(motion, xy)
    assert math.isnan(got[0].vx_mm_s)  # the touch: one centroid, no velocity
    for k in range(1, 40):
        lo = max(0, k - WINDOW + 1)
        v, _ = window_velocity(np.arange(lo, k + 1) * PERIOD_NS * 1e-9, xy[lo:k + 1])
        assert (got[k].vx_mm_s, got[k].vy_mm_s) == pytest.approx(tuple(v), rel=1e-9, abs=1e-9)


def test_dropped_frames_do_not_bend_the_velocity(motion) -> None:
    """The window's own timestamps are used: a slide seen with frames missing still gives its speed."""
    frames = np.array([0, 1, 2, 5, 6, 9, 10, 11, 15, 16])
    t_ns = frames * PERIOD_NS
    xy = np.outer(t_ns * 1e-9, (20.0, 0.0))
    got = _feed(motion, xy, t_ns=t_ns)
    assert got[-1].vx_mm_s == pytest.approx(20.0, rel=1e-6) and got[-1].vy_mm_s == pytest.approx(0.0, abs=1e-6)


def test_a_held_contact_never_slides_over_100_000_frames_of_its_noise(motion) -> None:
    """7 minutes at 240 fps of a held contact's centroid noise (sigma 0.01 mm, more than the simulator's)."""
    got = _feed(motion, _held(100_000, 0.01, seed=1))
    assert not any(c.sliding for c in got)


def test_a_slide_is_found_within_three_frames_and_ends_when_it_stops(motion) -> None:
    """Held for 1 s, then 10 mm/s along +x for 0.5 s, then held again."""
    held, moving = 240, 120
    path = np.zeros((held + moving + 240, 2))
    path[held:held + moving, 0] = 10.0 * PERIOD * np.arange(1, moving + 1)
    path[held + moving:, 0] = path[held + moving - 1, 0]
    got = _feed(motion, path + _held(len(path), 0.005, seed=2, at=(0.0, 0.0)))
    sliding = [k for k, c in enumerate(got) if c.sliding]
    assert sliding and held + 1 <= sliding[0] <= held + 3  # frame `held` is still in place; it moved after
    assert got[sliding[0]].slide_frame == sliding[0] and got[held + moving - 1].slide_frame == sliding[0]
    assert all(c.sliding for c in got[sliding[0]:held + moving])
    assert not any(c.sliding for c in got[held + moving + WINDOW:])
    assert got[-1].slide_frame == -1
    steady = np.array([(c.vx_mm_s, c.vy_mm_s) for c in got[held + WINDOW:held + moving]])
    assert np.sqrt(((steady - (10.0, 0.0)) ** 2).sum(axis=1).mean()) < 1.0


def test_a_small_vibration_is_not_a_slide(motion) -> None:
    """0.05 mm at 30 Hz (9.4 mm/s peak velocity) shakes the centroid but does not move the contact away."""
    t = np.arange(2400) * PERIOD
    xy = _held(2400, 0.004, seed=4) + np.c_[0.05 * np.sin(2 * np.pi * 30 * t), np.zeros_like(t)]
    xy[:240] = _held(240, 0.004, seed=5)  # a quiet second first
    assert not any(c.sliding for c in _feed(motion, xy))


def test_a_slow_creep_below_the_level_is_not_a_slide(motion) -> None:
    creep = 0.5 * MIN_SLIP_SPEED_MM_S
    xy = np.outer(np.arange(4800) * PERIOD, (creep, 0.0)) + _held(4800, 0.002, seed=6)
    assert not any(c.sliding for c in _feed(motion, xy))


def _faint(motion, strength: np.ndarray, seed: int) -> tuple[list[ContactEstimate], np.ndarray]:
    """One contact of the given strengths, its centroid noise in inverse proportion to them (0.004 mm at
    100); the estimates, and their speeds."""
    xy = 1.0 + np.random.default_rng(seed).normal(0.0, 1.0, (strength.size, 2)) * (0.4 / strength)[:, None]
    got = []
    for k in range(strength.size):
        c = ContactEstimate(contact=True, x_mm=float(xy[k, 0]), y_mm=float(xy[k, 1]), contact_id=3, touch_frame=0,
                            strength=float(strength[k]))
        motion.update([c], 1, k, k * PERIOD_NS)
        got.append(c)
    return got, np.hypot([c.vx_mm_s for c in got], [c.vy_mm_s for c in got])


def test_a_press_being_lifted_is_not_a_slide(motion) -> None:
    """Held at strength 100 for a second, then lifted over 0.1 s: the strength falls to 1 % and its centroid
    wanders as much as a faint contact's does (the noise in inverse proportion to the strength)."""
    got, speeds = _faint(motion, np.r_[np.full(240, 100.0), 100.0 * np.geomspace(1.0, 0.01, 24)], seed=7)
    assert not any(c.sliding for c in got)
    assert speeds[240:].max() > MIN_SLIP_SPEED_MM_S  # it did wander as fast as a slow slide


def test_a_press_being_pressed_in_is_not_a_slide(motion) -> None:
    """A first contact pressed in over 0.1 s (its strength growing from 1 % to full), its centroid wandering as
    a faint contact's does, then held: never a slide."""
    got, speeds = _faint(motion, np.r_[100.0 * np.geomspace(0.01, 1.0, 24), np.full(240, 100.0)], seed=8)
    assert not any(c.sliding for c in got)
    assert speeds[1:24].max() > 3 * MIN_SLIP_SPEED_MM_S  # it did wander fast


def test_a_new_touch_and_a_tare_start_the_window_again(motion) -> None:
    xy = np.outer(np.arange(20) * PERIOD, (50.0, 0.0))
    got = _feed(motion, xy)
    assert got[-1].sliding
    again = _feed(motion, xy[:1] + 5.0, cid=7, first_frame=20)  # the same id handed out again: a touch
    assert math.isnan(again[0].vx_mm_s) and not again[0].sliding
    motion.reset()
    after = _feed(motion, xy[:2], cid=9, first_frame=30)
    assert math.isnan(after[0].vx_mm_s) and after[1].vx_mm_s == pytest.approx(50.0)


def test_contacts_that_are_gone_are_forgotten(motion) -> None:
    """Contact 1 goes; 20 other contacts come and go after it; 2 keeps its window throughout."""
    a = ContactEstimate(contact=True, x_mm=0.0, y_mm=0.0, contact_id=1, touch_frame=0)
    b = ContactEstimate(contact=True, x_mm=5.0, y_mm=5.0, contact_id=2, touch_frame=0)
    motion.update([a, b], 2, 0, 0)
    for k in range(1, 21):
        b.x_mm = 5.0 + 0.01 * k
        other = ContactEstimate(contact=True, x_mm=-5.0, y_mm=0.0, contact_id=100 + k, touch_frame=k)
        motion.update([b, other], 2, k, k * PERIOD_NS)
        assert math.isnan(other.vx_mm_s) and b.vx_mm_s == pytest.approx(0.01 / PERIOD)


def test_the_kernels_motion_is_the_reference() -> None:
    """Random contacts touching, moving, sliding, fading, stopping and releasing over 10 000 frames, with frames
    dropped and clock jitter: the kernel's velocities, slip states and slide frames are the reference's."""
    if not BUILT:
        pytest.skip("the compiled kernel is not built")
    rng = np.random.default_rng(12)
    ref, kern = ContactMotion(), compiled.compiled_motion()
    live: dict[int, list[float]] = {}  # id -> [x, y, vx, vy, touch frame, strength]
    next_id, t_ns, slides = 1, 0, 0
    for frame in range(10_000):
        t_ns += PERIOD_NS * (1 + int(rng.uniform() < 0.02)) + int(rng.integers(-20_000, 20_000))
        if live and rng.uniform() < 0.004:
            live.pop(int(rng.choice(list(live))))
        if len(live) < 4 and rng.uniform() < 0.01:
            live[next_id] = [rng.uniform(-8, 8), rng.uniform(-8, 8), 0.0, 0.0, frame, 100.0]
            next_id = next_id % 255 + 1
        cs = []
        for cid, s in live.items():
            if rng.uniform() < 0.01:  # start or stop sliding
                s[2], s[3] = (0.0, 0.0) if s[2] or s[3] else tuple(rng.uniform(-60, 60, 2))
            s[0] += s[2] * PERIOD + rng.normal(0, 0.004)
            s[1] += s[3] * PERIOD + rng.normal(0, 0.004)
            s[5] = max(s[5] * rng.choice([1.0, 0.97, 1.02], p=[0.9, 0.05, 0.05]), 0.5)  # fading and growing
            cs.append((cid, s[0], s[1], int(s[4]), s[5]))
        a = [ContactEstimate(contact=True, x_mm=x, y_mm=y, contact_id=c, touch_frame=tf, strength=st)
             for c, x, y, tf, st in cs]
        b = [ContactEstimate(contact=True, x_mm=x, y_mm=y, contact_id=c, touch_frame=tf, strength=st)
             for c, x, y, tf, st in cs]
        ref.update(a, len(a), frame, t_ns)
        kern.update(b, len(b), frame, t_ns)
        for p, q in zip(a, b):
            assert (p.sliding, p.slide_frame) == (q.sliding, q.slide_frame)
            np.testing.assert_allclose((p.vx_mm_s, p.vy_mm_s), (q.vx_mm_s, q.vy_mm_s), rtol=1e-12, atol=1e-9)
            slides += p.slide_frame == frame
    assert slides > 25


def test_bunched_frame_times_give_no_velocity_where_the_camera_period_is_known(motion) -> None:
    """Issue 38 item 14: frame times closer than the camera can take them (queued frames handed over at once)
    gave -187 904 mm/s on a held contact. With the nominal period known, a window spanning less than half its
    nominal time has no velocity, and nothing slides on it; with the period unknown the window is fitted as it
    comes (the old behaviour, kept where nothing says better)."""
    xy = _held(30, 0.01, seed=4)
    t_ns = np.arange(30) * PERIOD_NS
    t_ns[20:] = t_ns[19] + np.arange(1, 11) * 1_000  # ten frames 1 µs apart
    motion.period_s = PERIOD
    got = _feed(motion, xy, t_ns=t_ns)
    assert all(math.isfinite(c.vx_mm_s) for c in got[1:20])  # the camera's own pace: velocities
    assert all(math.isnan(c.vx_mm_s) and math.isnan(c.vy_mm_s) for c in got[23:])  # the window bunched
    assert not any(c.sliding for c in got)
    t_ns[20:] = t_ns[19] + np.arange(1, 11) * PERIOD_NS // 3  # three times faster than declared: still bunched
    motion.reset()
    assert math.isnan(_feed(motion, xy, t_ns=t_ns, cid=8)[-1].vx_mm_s)
    t_ns[20:] = t_ns[19] + np.arange(1, 11) * (PERIOD_NS * 2 // 3)  # 1.5 x the pace: a velocity
    motion.reset()
    assert math.isfinite(_feed(motion, xy, t_ns=t_ns, cid=9)[-1].vx_mm_s)
    unknown = ContactMotion() if isinstance(motion, ContactMotion) else compiled.compiled_motion()
    t_ns[20:] = t_ns[19] + np.arange(1, 11) * 1_000
    last = _feed(unknown, xy, t_ns=t_ns, cid=10)[-1]
    assert math.hypot(last.vx_mm_s, last.vy_mm_s) > 1_000.0  # what it read before: a held contact at > 1 m/s


def test_a_frame_period_is_a_finite_number_of_seconds(motion) -> None:
    for bad in (-1.0, math.inf, math.nan):
        with pytest.raises(ValueError, match="period_s must be a finite number"):
            motion.period_s = bad
    motion.period_s = PERIOD
    assert motion.period_s == PERIOD
