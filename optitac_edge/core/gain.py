"""The frame's common-mode LED gain, measured from the brightest fibers and divided out (``compensate_gain``).

``ratio = (mean - black) / (baseline - black)`` per fiber is ``g (1 - d)``
with ``g`` the LED gain and ``d >= 0`` the darkening by a press, so the
brightest fibers measure ``g``: the median of the ratios within ``delta`` (the
off level) of the cluster around the upper quartile, twice. The gain may
differ from the last contact-free frame's by a tolerance plus a drift rate
times the time since, no more: a large press cannot pass for a dimming.

A sudden common-mode change of the light (the LED supply drooping when the
gripper's motors start) moves the brightest cluster beyond that band too, but
then most fibers agree on the new gain (a press darkens only the fibers under
it, by varying amounts): when at least :data:`COMMON_MODE_FRACTION` of the live
fibers lie within the cluster's width of the new gain, and the change is
larger than the truncation level (smaller ones cannot make a contact), the
new gain is taken at once and the change is counted (:attr:`GainCompensation.light_changes`)
instead of being reported as a contact over the whole surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from optitac_edge.core.baseline import Baseline

#: A jump of the brightest cluster's gain is a common-mode change of the light when at least this
#: fraction of the live fibers agree with the new gain (within the cluster's width).
COMMON_MODE_FRACTION = 0.6


@dataclass(frozen=True)
class LedGain:
    """The LED gain compensation's state after a frame (:attr:`Pipeline.led_gain
    <optitac_edge.core.pipeline.Pipeline.led_gain>`), whichever runs the frames.

    Attributes
    ----------
    gain : float
        The gain the frame was compensated with (relative to the baseline's light).
    frame_gain : float
        The frame's own estimate, before the limit.
    reference : float
        The last contact-free frame's gain (the limit's centre).
    reference_ns : int
        Its time, ns.
    light_changes : int
        Common-mode changes of the light taken at once, since the pipeline was built.
    """

    gain: float
    frame_gain: float
    reference: float
    reference_ns: int
    light_changes: int


class GainCompensation:
    """The LED gain of each frame and the gain-compensated signal; allocates nothing per frame.

    Parameters
    ----------
    live : ndarray of int, shape (L,)
        Indices of the fibers the gain is measured on (the live ones).
    n_fibers : int
        N.
    black_level : float
        Gray level of a fiber with no light.
    rate_per_s : float
        How fast the gain may drift without evidence, per s.
    relative : bool
        The signal in relative units (else gray levels).
    """

    def __init__(self, live: np.ndarray, n_fibers: int, black_level: float, rate_per_s: float,
                 relative: bool) -> None:
        self._live_idx = np.asarray(live, dtype=np.intp)
        self._live = np.zeros(self._live_idx.size, dtype=np.float32)  # the live fibers' ratios, sorted
        self._unsorted = np.zeros(self._live_idx.size, dtype=np.float32)
        self._live_row, self._unsorted_row = self._live.reshape(1, -1), self._unsorted.reshape(1, -1)
        # 0-d operands filled per frame: a Python or numpy scalar given to a ufunc becomes a new array
        self._probe = np.zeros((), dtype=np.float32)
        self._below = np.zeros(self._live_idx.size, dtype=bool)  # searchsorted as a count: no result array
        self._scale = np.zeros((), dtype=np.float32)
        self._one = np.ones((), dtype=np.float32)
        #: Per-fiber ratio of the last frame (scratch; see :meth:`rest_means`).
        self._ratio = np.zeros(n_fibers, dtype=np.float32)
        self._black = np.full((), black_level, dtype=np.float32)  # 0-d: no new array per ufunc call
        self._rate = float(rate_per_s) * 1e-9  # per ns
        self._relative = relative
        #: The gain the last frame was compensated with (1 before any frame).
        self.gain = 1.0
        #: The last frame's own gain estimate, before the limit.
        self.frame_gain = 1.0
        #: The last contact-free frame's gain and its time, ns.
        self.reference = 1.0
        self.reference_ns = 0
        self._tolerance = 0.0
        self._keep = 1.0
        self._widen = 1.0
        self._significant = 0.0
        #: The last frame's gain was a common-mode change of the light, taken at once.
        self.light_changed = False
        self._held = False  # the last frame's own estimate was out of the band, and held to it
        #: Common-mode changes of the light taken since construction.
        self.light_changes = 0

    def state(self) -> LedGain:
        """The state after the last frame."""
        return LedGain(self.gain, self.frame_gain, self.reference, self.reference_ns, self.light_changes)

    def set_levels(self, delta: float, tolerance: float, significant: float) -> None:
        """``delta``: the cluster width (the off level, relative); ``tolerance``: the gain change
        allowed without evidence (relative); ``significant``: the smallest change of the light that
        could make a contact (the truncation level, relative)."""
        self._keep = 1.0 - delta
        self._widen = 1.0 + delta
        self._tolerance = tolerance
        self._significant = significant

    def reset_gain(self, now_ns: int = 0) -> None:
        """Gain 1 from ``now_ns`` on (a new baseline)."""
        self.reference = self.gain = 1.0
        self.reference_ns = now_ns

    def _agree(self, g: float) -> int:
        """How many live fibers' ratios lie within the cluster's width of gain ``g`` (sorted: two bisections)."""
        return self._count_below(g * self._widen, inclusive=True) - self._count_below(g * self._keep)

    def _count_below(self, value: float, inclusive: bool = False) -> int:
        """Live ratios < ``value`` (<= with ``inclusive``), compared in float32: ``searchsorted`` on the
        sorted ratios (left, or right side), without the result array it allocates."""
        self._probe.fill(value)
        (np.less_equal if inclusive else np.less)(self._live, self._probe, out=self._below)
        return int(np.count_nonzero(self._below))

    def contact_free(self, now_ns: int) -> None:
        """The last frame had no contact: its own gain estimate is the reference from now on, unless
        that estimate was held to the band for a change that could make a contact and that most fibers
        did not share: then the brightest cluster was not the rest light (fibers brighter than their
        baseline, :class:`~optitac_edge.core.baseline.BrightFibers`), and the reference stays."""
        if not self._held:
            self.reference, self.reference_ns = self.frame_gain, now_ns

    def signal(self, means: np.ndarray, baseline: Baseline, now_ns: int, out: np.ndarray) -> np.ndarray:
        """The inverted signal of ``means`` with the frame's gain divided out, into ``out`` (shape (N,)).

        Relative units: ``1 - ratio / g``; gray levels: ``(baseline - black) - (mean - black) / g``.
        """
        ratio = np.subtract(means, self._black, out=self._ratio)
        ratio *= baseline.inv_level
        live = self._live
        ratio.take(self._live_idx, out=self._unsorted, mode="wrap")
        # OpenCV's sort into the buffer: ndarray.sort allocates a work buffer every call
        cv2.sort(self._unsorted_row, cv2.SORT_EVERY_ROW | cv2.SORT_ASCENDING, dst=self._live_row)
        n = live.size
        g = float(live[(3 * (n - 1)) // 4])
        keep = self._keep
        for _ in range(2):
            j = self._count_below(g * keep)
            if j >= n:  # no fiber in the cluster (all ratios <= 0: light at or below black): keep g
                break
            g = 0.5 * (float(live[(j + n - 1) // 2]) + float(live[(j + n) // 2]))
        self.frame_gain = g
        self.light_changed = False
        band = self._tolerance + self._rate * float(now_ns - self.reference_ns)
        change = abs(g - self.reference)
        self._held = False
        if change > band and change > self._significant and self._agree(g) >= COMMON_MODE_FRACTION * n:
            self.reference, self.reference_ns = g, now_ns  # the light changed, not the skin
            self.light_changed = True
            self.light_changes += 1
        elif change > band:
            g = self.reference - band if g < self.reference else self.reference + band
            # a change that could make a contact, and not common-mode: not the rest light
            self._held = change > self._significant
        self.gain = g = max(g, 1e-3)
        self._scale.fill(-1.0 / g)
        np.multiply(ratio, self._scale, out=out)
        out += self._one
        if not self._relative:
            out *= baseline.level
        return out

    def rest_means(self, baseline: Baseline) -> np.ndarray:
        """The last frame's fiber means with the gain divided out (what the baseline tracks: per-fiber
        drift, not the LED gain). Overwrites the ratio scratch; a view valid until the next frame."""
        means = np.multiply(self._ratio, baseline.level, out=self._ratio)
        self._scale.fill(self.gain)
        means /= self._scale
        means += self._black
        return means
