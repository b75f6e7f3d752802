"""Vibration: how much of a sensor's fiber signal lies above a cut-off frequency, frame by frame.

Incipient slip, a texture dragged over the skin and a shaking object show
first as fast, small changes of the fibers under a contact, well before the
contact's centroid moves by a fraction of a millimetre. At 240 fps the camera
sees up to 120 Hz.

Each live fiber's signal goes through a second-order Butterworth high-pass at
:data:`CUTOFF_HZ` (designed by the bilinear transform for the camera's nominal
frame rate, :attr:`VibrationMeter.period_s`; where that is not known, for the
first interval the frames arrive at): a held press, a slowly growing or shrinking one and a
steady ramp of light give nothing in steady state (the filter's double zero
at DC). The frame's *vibration* is the mean square of that high-passed signal
over the fibers under a contact (signal above the truncation level, when at
least :data:`MIN_FIBERS` are; else every live fiber), the frame's common part
taken out (an LED changing), in units of the same mean square over the fibers
away from any contact (the sensor's noise: learned over the first
:data:`LEARN_FRAMES` frames after the baseline, then followed), averaged over
the last :data:`WINDOW` frames. At rest and during a quiet hold it reads about 1.

It *vibrates* when that number exceeds its quiet value (learned as it goes,
starting at 1) by :data:`ON_SIGMAS` times the spread a mean of that many noise
squares has, and stops below half that excess. A touch, a release and a fast
slide have energy above the cut-off too and raise it while they last.

numpy on the fibers, a few operations per frame, no allocation per frame.
"""

from __future__ import annotations

import math

import numpy as np

from optitac_edge.core.motion import checked_period

#: The high-pass's cut-off, Hz, lowered to RATE_FRACTION x the frame rate for slow cameras.
CUTOFF_HZ = 20.0
RATE_FRACTION = 0.3
#: Frames the vibration is averaged over (5: 21 ms at 240 fps).
WINDOW = 5
#: Vibrating when the level exceeds its quiet value by this many spreads of a mean of noise squares over
#: the fibers and frames it is taken from (1 + 6 sqrt(2 / (n_fibers x WINDOW / 2))) times the quiet value:
#: 1.36 over 217 fibers, 1.76 over 50, 3.0 over 7); no longer when below half that excess.
ON_SIGMAS = 6.0
#: Fewest fibers a mean is taken over: a contact's fibers when it has as many, else every live fiber.
MIN_FIBERS = 7
#: Contact-free frames after the baseline the rest noise is learned from before the first figure.
LEARN_FRAMES = 10
#: Time constants the quiet level follows with, s: while quiet, and while vibrating (a lasting change of
#: the noise is taken as the new quiet after a while).
QUIET_TAU_S = 2.0
VIBRATING_TAU_S = 30.0


def butter2_highpass(cutoff_hz: float, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """A second-order Butterworth high-pass by the bilinear transform (``scipy.signal.butter(2, ., 'high')``).

    Parameters
    ----------
    cutoff_hz, rate_hz : float
        The -3 dB frequency and the sampling rate, Hz (``0 < cutoff_hz < rate_hz / 2``).

    Returns
    -------
    b, a : ndarray, shape (3,), float64
        Numerator and denominator, ``a[0] = 1``.

    Raises
    ------
    ValueError
        When the cut-off is not between 0 and the Nyquist frequency.
    """
    if not (0.0 < cutoff_hz < rate_hz / 2.0 and math.isfinite(rate_hz)):
        raise ValueError(f"a high-pass cut-off must lie in (0, {rate_hz / 2:g}) Hz, got {cutoff_hz!r}")
    k = math.tan(math.pi * cutoff_hz / rate_hz)
    norm = 1.0 / (1.0 + math.sqrt(2.0) * k + k * k)
    b = np.array([norm, -2.0 * norm, norm])
    a = np.array([1.0, 2.0 * (k * k - 1.0) * norm, (1.0 - math.sqrt(2.0) * k + k * k) * norm])
    return b, a


class VibrationMeter:
    """The vibration of one sensor's fibers, frame by frame (see the module's description).

    Parameters
    ----------
    signal : ndarray, shape (N,), float32
        The buffer every frame's inverted per-fiber signal is in (the pipeline's), read by :meth:`update`.
    live : ndarray, shape (N,), bool
        The fibers that carry light (dead fibers are left out).

    Attributes
    ----------
    level : float
        The last frame's vibration, in units of the high-passed noise at rest; NaN while the rest noise is
        being learned.
    vibrating : bool
        The level is above its quiet value by :data:`ON_SIGMAS` spreads (until it falls below half that).
    began : bool
        ``vibrating`` turned on in the last frame (the event).
    quiet : float
        The level's quiet value the ratios apply to.
    """

    def __init__(self, signal: np.ndarray, live: np.ndarray) -> None:
        self._signal = signal
        self._live = np.flatnonzero(np.asarray(live, dtype=bool))
        n = self._live.size
        self._x = np.zeros(n, dtype=np.float32)
        self._h = np.zeros(n, dtype=np.float32)
        self._z1 = np.zeros(n, dtype=np.float32)
        self._z2 = np.zeros(n, dtype=np.float32)
        self._tmp = np.zeros(n, dtype=np.float32)
        self._mask = np.zeros(n, dtype=bool)
        self._ring = [0.0] * WINDOW
        self._period_s = 0.0
        self.reset()

    @property
    def period_s(self) -> float:
        """The camera's nominal frame period, s, the filter is designed for (0: not known, the first frame
        interval is taken)."""
        return self._period_s

    @period_s.setter
    def period_s(self, value: float) -> None:
        self._period_s = checked_period(value, "VibrationMeter")

    def reset(self) -> None:
        """Start again (a tare, a new baseline): the filter from the next frame's signal, the rest noise
        learned again."""
        self._coef: tuple[float, float, float, float, float] | None = None
        self._unit = 0.0  # mean square of the high-passed signal at rest, per fiber
        self._learned = 0
        self._ring[:] = [0.0] * WINDOW
        self._k = 0
        self.level = math.nan
        self.quiet = 1.0
        self.vibrating = self.began = False

    def update(self, trunc: float, dt_ns: int) -> float:
        """Add the frame in the signal buffer; returns :attr:`level`.

        Parameters
        ----------
        trunc : float
            The truncation level, signal units: fibers above it are under a contact.
        dt_ns : int
            Time since the previous frame, ns (without :attr:`period_s` the filter is designed from the first
            one > 0).
        """
        x = np.take(self._signal, self._live, out=self._x)
        self.began = False
        if self._coef is None:
            if self._period_s > 0.0:
                self._design(x, 1.0 / self._period_s)
            elif dt_ns > 0:
                self._design(x, 1e9 / dt_ns)
            return self.level
        b0, b1, a1, a2, b2 = self._coef  # direct form II transposed, every fiber at once
        h, z1, z2, tmp = self._h, self._z1, self._z2, self._tmp
        np.multiply(x, b0, out=h)
        h += z1
        np.multiply(x, b1, out=z1)
        z1 += z2
        np.multiply(h, a1, out=tmp)
        z1 -= tmp
        np.multiply(x, b2, out=z2)
        np.multiply(h, a2, out=tmp)
        z2 -= tmp
        mask = np.greater(x, trunc, out=self._mask)
        n_on = int(np.count_nonzero(mask))
        h -= h.mean()
        np.multiply(h, h, out=tmp)
        total = float(tmp.sum())
        on = float(np.sum(tmp, where=mask)) if n_on else 0.0
        n_off = tmp.size - n_on
        if n_off >= MIN_FIBERS:  # the fibers away from any contact: the noise's unit
            self._learn((total - on) / n_off, dt_ns)
        if self._learned < LEARN_FRAMES:
            return self.level
        if n_on >= MIN_FIBERS:
            return self._judge(on / n_on / self._unit, n_on, dt_ns)
        return self._judge(total / tmp.size / self._unit, tmp.size, dt_ns)

    def _design(self, x: np.ndarray, rate_hz: float) -> None:
        b, a = butter2_highpass(min(CUTOFF_HZ, RATE_FRACTION * rate_hz), rate_hz)
        self._coef = (float(b[0]), float(b[1]), float(a[1]), float(a[2]), float(b[2]))
        # the filter's state at rest for this signal: a constant input gives 0 out
        np.multiply(x, -b[0], out=self._z1)
        np.multiply(x, b[2], out=self._z2)

    def _learn(self, ms: float, dt_ns: int) -> None:
        if self._learned < LEARN_FRAMES:
            self._learned += 1
            self._unit += (ms - self._unit) / self._learned
        else:
            self._unit += (ms - self._unit) * min(1.0, dt_ns * 1e-9 / QUIET_TAU_S)

    def _judge(self, ratio: float, n_fibers: int, dt_ns: int) -> float:
        ring = self._ring
        if math.isnan(self.level):  # the first figure: the window starts full of it
            ring[:] = [ratio] * WINDOW
        ring[self._k] = ratio
        self._k = (self._k + 1) % WINDOW
        level = self.level = sum(ring) / WINDOW
        quiet = self.quiet
        # the spread of a mean of n_fibers x WINDOW squares of noise (half of them independent)
        excess = ON_SIGMAS * math.sqrt(2.0 / (n_fibers * WINDOW * 0.5))
        top = quiet * (1.0 + excess)  # the on level; off below half its excess
        if self.vibrating:
            if level < quiet * (1.0 + 0.5 * excess):
                self.vibrating = False
            tau = VIBRATING_TAU_S
        elif level > top:
            self.vibrating = self.began = True
            tau = VIBRATING_TAU_S
        else:
            tau = QUIET_TAU_S
        self.quiet = quiet + (min(level, top) - quiet) * min(1.0, dt_ns * 1e-9 / tau)
        return level
