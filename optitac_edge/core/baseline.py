"""The per-fiber rest light: averaged over the first frames, then (optionally) tracked slowly.

The first ``n_frames`` frames' fiber means are averaged into the baseline
(the paper's 5). With ``track_baseline`` the baseline then follows the fiber
means on quiet contact-free frames with a time constant of seconds (LED
warm-up, drift), but not within ``holdoff_s`` of a contact's end.
"""

from __future__ import annotations

import math

import cv2
import numpy as np


class Baseline:
    """Rest light of N fibers; allocates nothing per frame.

    Parameters
    ----------
    n_fibers : int
        N.
    n_frames : int
        Frames averaged into the baseline (at least 1).
    black_level : float
        Gray level of a fiber with no light; :attr:`level` is the light above it.
    tau_s, holdoff_s : float
        Tracking time constant, and the time after a contact's end without tracking, s.
    """

    def __init__(self, n_fibers: int, n_frames: int, black_level: float, tau_s: float, holdoff_s: float) -> None:
        self._default_frames = self.n_frames = max(int(n_frames), 1)
        #: Per-fiber baseline gray levels, shape (N,), float32 (zeros until ready).
        self.values = np.zeros(n_fibers, dtype=np.float32)
        #: ``max(values - black_level, 1)``, shape (N,), float32: the rest light above black.
        self.level = np.ones(n_fibers, dtype=np.float32)
        #: ``1 / level``, shape (N,), float32.
        self.inv_level = np.ones(n_fibers, dtype=np.float32)
        # 0-d operands (a scalar given to a ufunc becomes a new array every call)
        self._black = np.full((), black_level, dtype=np.float32)
        self._one = np.ones((), dtype=np.float32)
        self._alpha = np.zeros((), dtype=np.float32)
        self._sum = np.zeros(n_fibers, dtype=np.float64)
        self._count = 0
        self._work = np.zeros(n_fibers, dtype=np.float32)
        self._sorted = np.zeros((1, n_fibers), dtype=np.float32)
        self._mid = n_fibers // 2
        self._tau_ns = float(tau_s) * 1e9
        self._holdoff_ns = float(holdoff_s) * 1e9

    @property
    def ready(self) -> bool:
        """The first ``n_frames`` frames have been averaged."""
        return self._count >= self.n_frames

    def reset(self, n_frames: int | None = None) -> None:
        """Start again: the next ``n_frames`` frames (default: as many as at construction) are averaged (tare)."""
        self.n_frames = self._default_frames if n_frames is None else max(int(n_frames), 1)
        self._sum.fill(0.0)
        self._count = 0

    def add(self, means: np.ndarray) -> bool:
        """Average one more frame's fiber means (shape (N,), float32); True when the baseline just became ready."""
        self._sum += means
        self._count += 1
        if self._count < self.n_frames:
            return False
        np.multiply(self._sum, 1.0 / self.n_frames, out=self.values, casting="same_kind")
        self._updated()
        return True

    def _updated(self) -> None:
        """The light above black and its reciprocal after a change (N values)."""
        np.subtract(self.values, self._black, out=self.level)
        np.maximum(self.level, self._one, out=self.level)
        np.reciprocal(self.level, out=self.inv_level)

    def raise_to(self, rest: np.ndarray, signal: np.ndarray, level: float, common: float = 0.0) -> int:
        """Set the baseline of the fibers brighter than it (``signal <= common - level``) to ``rest`` (their
        light now, gray levels, shape (N,)); returns how many (see :class:`BrightFibers`)."""
        bright = signal <= common - level
        self.values[bright] = rest[bright]
        self._updated()
        return int(np.count_nonzero(bright))

    def track(self, means: np.ndarray, signal: np.ndarray, off_level: float, now_ns: int, dt_ns: int,
              contact_end_ns: int | None) -> bool:
        """Follow ``means`` on a quiet contact-free frame; whether the baseline moved.

        Quiet: no fiber's ``signal`` departs from the common (median) level by
        ``off_level`` or more (a uniform brightness drift is what the tracking
        is for; a press is local); and not within ``holdoff_s`` of ``contact_end_ns``.
        The step is ``1 - exp(-dt / tau)`` of the difference, ``dt`` capped at tau.
        """
        if contact_end_ns is not None and now_ns - contact_end_ns < self._holdoff_ns:
            return False
        work = self._work
        # the median by OpenCV's sort into a buffer (ndarray.partition allocates a work buffer)
        cv2.sort(signal.reshape(1, -1), cv2.SORT_EVERY_ROW | cv2.SORT_ASCENDING, dst=self._sorted)
        common = self._sorted[0, self._mid:self._mid + 1]
        np.subtract(signal, common, out=work)
        np.abs(work, out=work)
        if cv2.minMaxLoc(work)[1] >= off_level:
            return False
        self._alpha.fill(1.0 - math.exp(-min(float(dt_ns), self._tau_ns) / self._tau_ns))
        diff = np.subtract(means, self.values, out=self._work)
        diff *= self._alpha
        self.values += diff
        self._updated()
        return True


#: Fibers brighter than their baseline for this long mean the baseline was taken over a press, s.
BRIGHT_HOLD_S = 0.25


class BrightFibers:
    """Fibers brighter than their baseline: a baseline taken while the skin was pressed.

    A press only darkens the fibers under it, so a fiber whose light stays above
    its baseline by the contact-off level cannot be explained by the skin: its
    baseline was taken while something pressed there (the service started, or
    was tared, during a grasp) and the press has gone. Such fibers read as
    negative signal, hide a new press at the same place, bias the gain estimate
    (the brightest fibers are no longer the rest light) and keep the baseline
    from tracking (it tracks only quiet frames). When some fiber has been that
    bright for :data:`BRIGHT_HOLD_S` and the frame has no contact, :meth:`check`
    says so, and :meth:`Baseline.raise_to` raises those fibers' baseline to
    their light (a fiber brighter than its baseline is not pressed now; the
    others keep theirs).

    Brighter than what: with the LED gain divided out (``compensate_gain``)
    the rest light is 0 signal; without it, a uniform change of the light moves
    every fiber alike and is no press, so brightness is measured from the
    common (median) level instead. Costs one ``minMaxLoc`` of N values per frame
    (with the common level, one sort of them too); allocates nothing but when it
    acts.

    Parameters
    ----------
    n_fibers : int
        N.
    from_common : bool
        Measure brightness from the signal's median, not from 0 (no gain compensation).
    hold_s : float
        How long some fiber must stay that bright, s (frame timestamps).
    """

    def __init__(self, n_fibers: int, from_common: bool, hold_s: float = BRIGHT_HOLD_S) -> None:
        self._hold_ns = int(hold_s * 1e9)
        self._since_ns: int | None = None
        self._from_common = from_common
        self._sorted = np.zeros((1, max(n_fibers, 1)), dtype=np.float32)
        self._mid = n_fibers // 2
        #: The level brightness was measured from in the last :meth:`check` (signal units).
        self.common = 0.0

    def reset(self) -> None:
        """A new baseline: nothing is bright."""
        self._since_ns = None

    def check(self, signal: np.ndarray, level: float, now_ns: int, contact_free: bool) -> bool:
        """Whether some fiber has been brighter than its baseline by ``level`` for the hold, and the frame
        has no contact (then the timer starts again).

        Parameters
        ----------
        signal : ndarray, shape (N,), float32
            The frame's inverted signal (positive where fibers darkened), signal units.
        level : float
            Brighter than the baseline (or the common level) by this much is not noise: the off level, signal units.
        now_ns : int
            The frame's time, ns.
        contact_free : bool
            The frame has no contact (its light is the skin at rest but where the baseline is wrong).
        """
        if self._from_common:
            cv2.sort(signal.reshape(1, -1), cv2.SORT_EVERY_ROW | cv2.SORT_ASCENDING, dst=self._sorted)
            lowest, self.common = float(self._sorted[0, 0]), float(self._sorted[0, self._mid])
        else:
            lowest = cv2.minMaxLoc(signal)[0]
        if lowest > self.common - level:
            self._since_ns = None
            return False
        if self._since_ns is None:
            self._since_ns = now_ns
        if not contact_free or now_ns - self._since_ns < self._hold_ns:
            return False
        self._since_ns = None
        return True
