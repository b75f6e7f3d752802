"""Contact motion (issue 29, its first part): a contact's velocity from a short window of its centroids.

The velocity of a tracked contact is the least-squares slope of its last ``W``
centroids against their times, each axis alone (the straight line through a
window: the same answer as a finite difference for ``W = 2``, and ``W``
samples' noise averaged for more). With the samples' times ``t_k`` and their
mean ``t̄``, the slope is::

    v = sum_k (t_k - t̄) p_k / sum_k (t_k - t̄)^2

a fixed weighting of the positions once the times are known. Its noise follows
from the centroid's own: with independent centroid noise ``σ`` (mm) on every
sample, the slope's standard error is ``σ / sqrt(sum_k (t_k - t̄)^2)`` (mm/s);
for ``W`` samples a frame period ``dt`` apart that is
``σ / (dt * sqrt(W (W² - 1) / 12))``. A level for "sliding" is then a
multiple of the velocity noise a held contact's own centroid noise gives, as
the contact levels are multiples of the fibers' noise.

:class:`ContactMotion` keeps each tracked contact's window and decides when
it slides (see there). :func:`window_velocity` is the same least-squares
slope in numpy, for analysis and tests.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from optitac_edge.core.contact import ContactEstimate


def window_velocity(t_s: np.ndarray, xy_mm: np.ndarray) -> tuple[np.ndarray, float]:
    """The least-squares velocity of a window of centroids, and the scatter about that straight line.

    Parameters
    ----------
    t_s : ndarray, shape (W,), float
        The samples' times, s (any origin; at least two distinct).
    xy_mm : ndarray, shape (W, 2), float
        The centroids, mm.

    Returns
    -------
    velocity : ndarray, shape (2,), float64
        d(x, y)/dt, mm/s.
    residual_rms : float
        The root mean square distance of the centroids from the fitted line,
        per axis, mm, with the fit's two degrees of freedom per axis taken
        out (``sqrt(sum r² / (2 (W - 2)))``); NaN for ``W = 2``.

    Raises
    ------
    ValueError
        On shapes that do not match, fewer than two samples or no spread in time.
    """
    t = np.asarray(t_s, dtype=np.float64)
    p = np.asarray(xy_mm, dtype=np.float64)
    if t.ndim != 1 or p.shape != (t.size, 2):
        raise ValueError(f"window_velocity: times (W,) and centroids (W, 2), got {t.shape} and {p.shape}")
    if t.size < 2:
        raise ValueError("window_velocity: at least two samples")
    dt = t - t.mean()
    s = float(dt @ dt)
    if not s > 0:
        raise ValueError("window_velocity: the samples' times do not differ")
    centred = p - p.mean(axis=0)
    velocity = dt @ centred / s
    if t.size == 2:
        return velocity, math.nan
    residual = centred - np.outer(dt, velocity)
    return velocity, math.sqrt(float((residual * residual).sum()) / (2 * (t.size - 2)))


def velocity_noise_factor(window: int, period_s: float) -> float:
    """``1 / sqrt(sum_k (t_k - t̄)^2)`` for ``window`` samples ``period_s`` apart, 1/s.

    Multiplied by a centroid's noise (mm, per axis) it gives the noise of
    :func:`window_velocity` per axis (mm/s).

    Raises
    ------
    ValueError
        For fewer than two samples or a period that is not positive and finite.
    """
    if window < 2:
        raise ValueError(f"a velocity window needs at least two samples, got {window}")
    if not (period_s > 0 and math.isfinite(period_s)):
        raise ValueError(f"the frame period must be a positive time, got {period_s!r}")
    return 1.0 / (period_s * math.sqrt(window * (window * window - 1) / 12.0))


#: Centroids in a contact's velocity window (5 frames: 16.7 ms at 240 fps, 83 ms at 60 fps).
WINDOW = 5
#: A contact slides when its speed exceeds this many times the velocity noise its own centroid noise gives...
SLIP_SIGMAS = 8.0
#: ... and at least this speed, mm/s ...
MIN_SLIP_SPEED_MM_S = 3.0
#: ... and it has moved at least this far (or ``SLIP_SIGMAS`` centroid noises) from where it was last at
#: rest, mm: a twentieth of the 1.5 mm fiber pitch, above a 0.05 mm vibration (gross motion, not shaking).
MIN_SLIP_SHIFT_MM = 0.075
#: A sliding contact is held again when its speed falls below this fraction of the level it slid at.
HOLD_FRACTION = 0.5
#: A contact whose window's strongest sample is more than this many times its faintest (or than the strength
#: its noise was measured at) is being pressed in or lifted: its centroid moves as its footprint grows or
#: shrinks, and no slide is judged.
STEADY_RATIO = 2.0
#: The centroid noise a contact starts with, mm, before its own is known (or the last contact's).
PRIOR_NOISE_MM = 0.01
#: Weight of one held frame's window in a contact's centroid noise and in where it rests (running means of
#: ~20 frames).
NOISE_RATE = 0.05
#: A window whose frames span less than this fraction of their nominal time (``(W - 1)`` camera periods) has no
#: velocity: timestamps bunched closer than the camera can take frames (a driver handing over queued frames at
#: once, a clock step) would divide a centroid's noise by almost nothing (-187 904 mm/s on a held contact).
MIN_SPAN_FRACTION = 0.5


def checked_period(value: float, who: str) -> float:
    """``value`` as a frame period, s: a finite number >= 0 (0: not known).

    Raises
    ------
    ValueError
        Otherwise, naming ``who``.
    """
    v = float(value)
    if not (v >= 0.0 and math.isfinite(v)):
        raise ValueError(f"{who}.period_s must be a finite number of seconds >= 0, got {value!r}")
    return v


class _Track:
    """One contact's window of centroids (a ring), its centroid noise and its slip state."""

    __slots__ = ("ax", "ay", "head", "n", "noise", "s", "slide_frame", "sliding", "strength", "t", "x", "y")

    def __init__(self, noise: float, strength: float) -> None:
        self.t = [0.0] * WINDOW
        self.x = [0.0] * WINDOW
        self.y = [0.0] * WINDOW
        self.s = [0.0] * WINDOW
        self.n = self.head = 0
        self.noise = noise
        self.strength = strength  # the contact's strength its noise was measured at (NaN: not known)
        self.sliding = False
        self.slide_frame = -1
        self.ax = self.ay = math.nan


class ContactMotion:
    """Every tracked contact's velocity and slip state, frame after frame.

    Per contact id (from :class:`~optitac_edge.core.tracking.ContactTracker`) it
    keeps the last :data:`WINDOW` centroids with their times and fits their
    least-squares velocity (as :func:`window_velocity`). While the contact is
    held, the scatter of its window about that line is its centroid noise
    ``σ`` (a running mean, starting from the last contact's). The contact
    *slides* when, over a full window, its speed exceeds
    ``max(SLIP_SIGMAS · σ · f, MIN_SLIP_SPEED_MM_S)`` (``f`` the window's
    :func:`velocity_noise_factor`) and it has moved more than
    ``max(MIN_SLIP_SHIFT_MM, SLIP_SIGMAS · σ)`` from where it rests (a running
    mean of its held window's centre);
    it is held again when its speed falls below :data:`HOLD_FRACTION` of that
    level. A breathing or growing press, an LED change or a small vibration
    moves the centroid little and slowly, and raises ``σ`` while it lasts. A
    contact's centroid is the noisier the fainter it is, in inverse proportion
    to its strength: ``σ`` is scaled by the strength it was measured at (its
    running mean while held; the window's strongest if that is stronger) over
    the window's faintest; beyond :data:`STEADY_RATIO` the press is being
    pressed in or lifted, its footprint and centroid change with its depth,
    and no slide is judged (where it rests follows it).

    Pure Python on at most a few contacts; nothing is allocated per frame but
    a track when a contact touches.
    """

    def __init__(self) -> None:
        self._tracks: dict[int, _Track] = {}
        self._prior = PRIOR_NOISE_MM
        self._prior_strength = math.nan
        self._period_s = 0.0

    @property
    def period_s(self) -> float:
        """The camera's nominal frame period, s (0: not known, no window is refused for its span)."""
        return self._period_s

    @period_s.setter
    def period_s(self, value: float) -> None:
        self._period_s = checked_period(value, "ContactMotion")

    def reset(self) -> None:
        """Forget every contact (a tare)."""
        self._tracks.clear()

    def update(self, contacts: Sequence[ContactEstimate], n: int, frame: int, now_ns: int) -> None:
        """Set ``vx_mm_s``, ``vy_mm_s``, ``sliding`` and ``slide_frame`` of the first ``n`` of ``contacts``
        (one frame's, with their ids), in place; forget the contacts that are gone."""
        tracks = self._tracks
        t_s = now_ns * 1e-9
        for i in range(n):
            c = contacts[i]
            track = tracks.get(c.contact_id)
            if track is None or c.touch_frame == frame:
                track = tracks[c.contact_id] = _Track(self._prior, self._prior_strength)
            _step(track, c, frame, t_s, self._period_s)
        if len(tracks) > n:
            self._forget(contacts, n)

    def _forget(self, contacts: Sequence[ContactEstimate], n: int) -> None:
        """Forget the contacts that are gone; the next contact starts from the noise of the (noisiest) one
        that had a full window."""
        alive = {contacts[i].contact_id for i in range(n)}
        prior, strength = -1.0, math.nan
        for cid in [cid for cid in self._tracks if cid not in alive]:
            track = self._tracks.pop(cid)
            if track.n >= WINDOW and track.noise > prior:
                prior, strength = track.noise, track.strength
        if prior >= 0.0:
            self._prior, self._prior_strength = prior, strength


def _step(track: _Track, c: ContactEstimate, frame: int, t_s: float, period_s: float) -> None:
    """Add ``c``'s centroid at ``t_s`` to its track; its velocity and slip state into ``c``.

    One pass over the window gives the slope and the scatter about it (sums of the centred products). A
    window spanning less than :data:`MIN_SPAN_FRACTION` of ``(n - 1) * period_s`` has no velocity.
    """
    x, y = c.x_mm, c.y_mm
    h = track.head
    ts, xs, ys = track.t, track.x, track.y
    ts[h], xs[h], ys[h] = t_s, x, y
    track.s[h] = c.strength
    track.head = (h + 1) % WINDOW
    n = track.n = track.n + 1 if track.n < WINDOW else WINDOW
    if n < 2:
        c.vx_mm_s = c.vy_mm_s = math.nan
        c.sliding, c.slide_frame = False, -1
        track.ax, track.ay = x, y
        return
    if n < WINDOW:  # the ring is filled from 0 until it is full
        ts, xs, ys = ts[:n], xs[:n], ys[:n]
    st = sx = sy = 0.0  # sums in order (as the kernel's; sum() compensates on Python 3.12)
    t_lo = t_hi = ts[0]
    for tk, xk, yk in zip(ts, xs, ys):
        st += tk
        sx += xk
        sy += yk
        t_lo, t_hi = min(t_lo, tk), max(t_hi, tk)
    if t_hi - t_lo < MIN_SPAN_FRACTION * (n - 1) * period_s:  # bunched frame times: no velocity
        c.vx_mm_s = c.vy_mm_s = math.nan
        c.sliding, c.slide_frame = track.sliding, track.slide_frame
        return
    tm, xm, ym = st / n, sx / n, sy / n
    stt = stx = sty = sxx = syy = 0.0
    for tk, xk, yk in zip(ts, xs, ys):
        dt, dx, dy = tk - tm, xk - xm, yk - ym
        stt += dt * dt
        stx += dt * dx
        sty += dt * dy
        sxx += dx * dx
        syy += dy * dy
    if not stt > 0.0:  # frames with one time: no velocity
        c.vx_mm_s = c.vy_mm_s = math.nan
        c.sliding, c.slide_frame = track.sliding, track.slide_frame
        return
    vx, vy = stx / stt, sty / stt
    c.vx_mm_s, c.vy_mm_s = vx, vy
    if n < WINDOW:
        track.ax, track.ay = xm, ym
        c.sliding, c.slide_frame = False, -1
        return
    _judge(track, c, frame, (vx, vy, stt, xm, ym, max(sxx - vx * stx + syy - vy * sty, 0.0)))
    c.sliding, c.slide_frame = track.sliding, track.slide_frame


def _judge(track: _Track, c: ContactEstimate, frame: int, fit: tuple[float, float, float, float, float, float]) -> None:
    """The slip state of a full window: ``fit`` = velocity, ``Σ (t - t̄)²``, the window's mean and the
    scatter about its line (``Σ r²``)."""
    vx, vy, stt, xm, ym, ss = fit
    speed = math.sqrt(vx * vx + vy * vy)
    # a fainter contact's centroid is the noisier in proportion (a press being pressed in or lifted): the
    # noise scaled by the strength it was measured at (or the window's strongest) over the window's faintest
    weakest, strongest = min(track.s), max(track.s)
    strongest = max(strongest, track.strength)
    ratio = strongest / weakest if weakest > 0.0 else (math.inf if strongest > 0.0 else 1.0)  # 1: none known
    if not ratio <= STEADY_RATIO:  # being pressed in or lifted: no slip judged, nothing learned
        if not track.sliding:
            track.ax, track.ay = xm, ym
        return
    noise = track.noise * ratio
    level = max(SLIP_SIGMAS * noise / math.sqrt(stt), MIN_SLIP_SPEED_MM_S)
    if track.sliding:
        if speed < HOLD_FRACTION * level:
            track.sliding, track.slide_frame = False, -1
            track.ax, track.ay = xm, ym
    elif speed > level and math.sqrt((c.x_mm - track.ax) ** 2 + (c.y_mm - track.ay) ** 2) > max(
            MIN_SLIP_SHIFT_MM, SLIP_SIGMAS * noise):
        track.sliding, track.slide_frame = True, frame
    else:  # held: the scatter about the line is its centroid noise; where it rests follows slowly
        strength = c.strength
        track.noise += NOISE_RATE * (math.sqrt(ss / (2 * (WINDOW - 2))) - track.noise)
        track.strength = strength if math.isnan(track.strength) else (track.strength
                                                                      + NOISE_RATE * (strength - track.strength))
        track.ax += NOISE_RATE * (xm - track.ax)
        track.ay += NOISE_RATE * (ym - track.ay)
