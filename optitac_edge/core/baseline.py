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
        self.n_frames = max(int(n_frames), 1)
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

    def reset(self) -> None:
        """Start again: the next ``n_frames`` frames are averaged (tare)."""
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
