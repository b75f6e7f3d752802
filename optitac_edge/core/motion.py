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

Plain numpy; nothing here keeps state (the tracker will hold each contact's
window).
"""

from __future__ import annotations

import math

import numpy as np


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
