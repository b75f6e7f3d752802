"""The LED brightness at calibration: the brightest setting at which no fiber saturates.

:func:`adjust_brightness_for_saturation` is pure: it lowers the brightness by
bisection until the brightest fibers stay below saturation, through a callback
that sets a brightness and returns the measured peak (the service's wiring
passes one that sets the LEDs, grabs a frame and takes :func:`fiber_peak`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


def fiber_peak(gray: np.ndarray, mask: np.ndarray | None = None, percentile: float = 99.9) -> float:
    """The ``percentile`` of the gray levels (of the fiber pixels where ``mask`` is true)."""
    pixels = gray[mask] if mask is not None else gray.ravel()
    if pixels.size == 0:
        return 0.0
    return float(np.percentile(pixels, percentile))


@dataclass(frozen=True)
class BrightnessAdjustment:
    """Result of :func:`adjust_brightness_for_saturation`.

    ``ok`` is false when even ``low`` saturates (then ``brightness`` is ``low``).
    """

    brightness: float
    peak: float
    measurements: int
    ok: bool


def adjust_brightness_for_saturation(
    read_peak: Callable[[float], float],
    *,
    max_peak: float = 230.0,
    start: float = 1.0,
    low: float = 0.0,
    steps: int = 6,
    tolerance: float = 8.0,
) -> BrightnessAdjustment:
    """Find the brightest setting in ``[low, start]`` whose peak stays at or below ``max_peak``.

    ``read_peak(b)`` must set the LEDs to ``b``, let a frame expose at that level
    and return its peak (e.g. :func:`fiber_peak` at the 99.9th percentile).
    If ``start`` does not exceed ``max_peak`` it is kept (one measurement).
    Otherwise bisection runs between ``low`` and ``start`` for at most ``steps``
    measurements, stopping early once a peak lands within ``tolerance`` below
    ``max_peak``. On return the LEDs are at the returned brightness (the last
    call to ``read_peak`` was with it).
    """
    if not 0.0 <= low <= start <= 1.0:
        raise ValueError(f"need 0 <= low <= start <= 1, got low={low!r} start={start!r}")
    n = 1
    peak = float(read_peak(start))
    if peak <= max_peak:
        return BrightnessAdjustment(start, peak, n, True)
    good: tuple[float, float] | None = None  # (brightness, peak) known not to saturate
    lo, hi = low, start
    last = start
    for _ in range(max(steps, 0)):
        mid = (lo + hi) / 2.0
        peak = float(read_peak(mid))
        n += 1
        last = mid
        if peak <= max_peak:
            good = (mid, peak)
            lo = mid
            if peak >= max_peak - tolerance:
                break
        else:
            hi = mid
    if good is None:  # nothing measured was below saturation: try the floor itself
        if last != low:
            peak = float(read_peak(low))
            n += 1
            last = low
        return BrightnessAdjustment(low, peak, n, peak <= max_peak)
    if last != good[0]:
        read_peak(good[0])  # leave the LEDs at the chosen level
        n += 1
    return BrightnessAdjustment(good[0], good[1], n, True)
