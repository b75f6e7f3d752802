"""The contact levels in signal units: truncation, contact off and contact on, and each fiber's band.

The paper truncates the surface at one calibrated threshold. With
``noise_levels`` the three levels are ``k`` times the noise of the typical
fiber (each at least a floor fraction of the rest light), or, where
``calibrate levels`` chose the on level on held-out presses
(``ContactOptions.on_level``), that level and the others in the same ratios;
with ``hysteresis`` a contact ends at the lower off level. The MCU's
SET_THRESHOLD overrides the on level (relative units of the rest light).

Each fiber's rest excursion is modelled in two parts, measured apart:

* its frame-to-frame **noise**, in gray levels (``calibrate fibers``: the
  camera's noise is additive, so a fiber's noise relative to its light grows
  as the light falls: a dim fiber, or one darkened by a press when the
  baseline was taken, is noisier in relative units);
* its slow **drift** since the baseline, relative to its light (``calibrate
  levels``: what every rest frame of the user's own recordings shows beyond
  the noise; minutes apart, a few percent).

At every new baseline ``e_i = sqrt(n_i^2 + d_i^2)``, ``n_i`` its noise relative
to its light, ``d_i`` its drift. A fiber whose ``e_i`` exceeds the typical
fiber's ``e_ref`` (the median over the live ones) by more than the estimate's
own uncertainty ``tol``, by the *excess* ``x = e_i / e_ref - 1 - tol > 0``, gets
a band by the source of its excursion (:func:`band_rows`, :func:`banded`):

* the drift's share ``w = d^2 / e^2`` of the excess, ``b_d = on x w``, is
  *subtracted* from every value: a drift is an offset on every frame, press or not;
* the rest, ``x' = x (1 - w)``, frame-to-frame noise (zero-mean), only
  *silences*, through a non-negative garrote: with ``u = (|s| - b_d)_+``,

    ``f(s) = sign(s) (u - c^2 / u)_+``,  ``c^2 = on^2 x' (1 + x')``,

  0 up to ``u = c``, twice as steep there, the value itself (less ``c^2 / u``,
  which falls as the press deepens) beyond.

Either way the fiber reaches the on level where ``s`` reaches ``on (1 + x)``,
so no fiber wanders further than ``e_ref (1 + tol)`` at the on level, and that
is the noise the levels are ``k`` times where no on level was chosen. A fiber
that wanders four times as much as the others then reaches the on level only
as often as they do, and raises no level of every fiber (a level over the
whole surface from its noisiest part did: on a real 61-fiber sensor the
contact level came out at 54 % darkening, and 1 of 30 presses was found).

Why by source: subtracting the whole band from every value moved a noisy
fiber's values inside every press (the simulator's dimmest fibers are banded
from their noise alone: a 217-fiber array read its widths ~10 % and its shapes
worse), and keeping every banded fiber's press values read the real sensor
worse (its banded fibers drift, and a drift rides on a press: 26 of 27 presses
and 2 of 15 false against 27 and 1, force 1.42-3.76 N against 1.33 N).
"""

from __future__ import annotations

import math

import numpy as np

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.options import ContactOptions

#: Bundle arrays, shape (N,): each fiber's frame-to-frame noise in the rest frames, gray levels (``calibrate
#: fibers``), and its drift since the baseline in use, relative units (``calibrate levels``).
NOISE_KEY, DRIFT_KEY = "levels/fiber_noise", "levels/fiber_drift"
#: The bundle's extra arrays indexed by fiber (shape (N,)): they move with a fiber's pixels when the fiber map
#: is reoriented.
FIBER_ARRAYS = (NOISE_KEY, DRIFT_KEY)
#: ``extra_meta`` of the levels: ``noise_samples``, ``drift_samples`` (how many values each fiber's figure is
#: from) and what ``calibrate levels`` found.
LEVELS_KEY = "levels"
#: A fiber's band starts this many standard errors of its excursion's estimate above the typical fiber's.
TOLERANCE_ERRORS = 2.0

#: compensate_gain: the LED gain of a frame with contact may differ from the last contact-free
#: frame's by this many truncation levels (plus ``gain_rate_per_s`` times the time since).
GAIN_TOLERANCE = 0.1


def band_rows(excess: np.ndarray, drift_share: np.ndarray, on: float, out: np.ndarray) -> np.ndarray:
    """Each fiber's band from its excess and the drift's share of it, as :func:`banded` reads them.

    Parameters
    ----------
    excess : ndarray, shape (N,)
        Each fiber's excess ``x`` beyond the typical fiber (<= 0: none).
    drift_share : ndarray, shape (N,)
        The drift's share ``w`` of its excursion's variance, 0..1.
    on : float
        The on level, signal units.
    out : ndarray, shape (2, N), float32
        Rows: ``c^2`` and the shift ``b_d`` (``b_d = on x w``, ``x' = x (1 - w)``, ``c^2 = on^2 x' (1 + x')``);
        a fiber with no excess: 0, 0.

    Returns
    -------
    ndarray
        ``out``.
    """
    x = np.maximum(np.asarray(excess, dtype=np.float64), 0.0)
    w = np.clip(np.asarray(drift_share, dtype=np.float64), 0.0, 1.0)
    shift = on * x * w
    rest = x * (1.0 - w)
    c2 = (on * on) * rest * (1.0 + rest)  # the garrote u - c^2 / u reaches on at u = on (1 + x')
    out[0] = c2
    out[1] = shift
    return out


def banded(signal: np.ndarray, bands: np.ndarray, magnitude: np.ndarray, work: np.ndarray) -> np.ndarray:
    """Each fiber's signal through its band, in place: ``sign(s) (u - c^2 / u)_+``, ``u = (|s| - b_d)_+``.

    Parameters
    ----------
    signal : ndarray, shape (N,), float32
        Each fiber's signal; overwritten.
    bands : ndarray, shape (2, N), float32
        ``c^2`` and the shift ``b_d`` per fiber (:func:`band_rows`).
    magnitude, work : ndarray, shape (N,), float32
        Buffers.

    Returns
    -------
    ndarray
        ``signal``; the float32 steps are the kernel's, one for one.
    """
    np.abs(signal, out=magnitude)
    np.subtract(magnitude, bands[1], out=magnitude)
    np.maximum(magnitude, 0.0, out=magnitude)  # u = (|s| - shift)+
    np.maximum(magnitude, np.float32(1e-30), out=work)
    np.divide(bands[0], work, out=work)
    np.subtract(magnitude, work, out=work)  # u - c^2 / u
    np.maximum(work, 0.0, out=work)
    return np.copysign(work, signal, out=signal)


def tolerance(samples: int) -> float:
    """How far above the typical fiber's excursion a fiber's may lie before it gets a band, as a fraction:
    :data:`TOLERANCE_ERRORS` relative standard errors of a standard deviation from ``samples`` values."""
    return TOLERANCE_ERRORS / math.sqrt(2.0 * max(samples - 1, 1))


def fiber_excess(excursion: np.ndarray, live: np.ndarray, samples: int) -> np.ndarray | None:
    """Each fiber's excursion beyond the typical fiber's, as a fraction of it: ``max(e / e_ref - 1 - tol, 0)``.

    Parameters
    ----------
    excursion : ndarray, shape (N,)
        Each fiber's rest excursion ``e_i`` (any units).
    live : ndarray of bool, shape (N,)
        The live fibers (the reference ``e_ref`` is their median; dead fibers get 0).
    samples : int
        How many values each ``e_i`` was estimated from: ``tol = 2 / sqrt(2 (samples - 1))``, twice the
        relative standard error of a standard deviation from that many, so only fibers clearly above the
        typical one get a band (about 2 % of them by chance).

    Returns
    -------
    ndarray, shape (N,), float32, or None
        None when no fiber is in excess (nothing to do per frame).
    """
    e = np.asarray(excursion, dtype=np.float64)
    alive = np.asarray(live, dtype=bool) & np.isfinite(e)
    if samples < 2 or not alive.any():
        return None
    ref = float(np.median(e[alive]))
    if not ref > 0:
        return None
    tol = tolerance(samples)
    out = np.where(alive, np.maximum(e / ref - 1.0 - tol, 0.0), 0.0).astype(np.float32)
    return out if bool(np.any(out > 0)) else None


def rest_excursion(noise_gray: np.ndarray | None, drift: np.ndarray | None, light: np.ndarray,
                   baseline_frames: int) -> np.ndarray:
    """Each fiber's rest excursion, relative units: ``sqrt((noise / light)^2 (1 + 1 / baseline_frames) +
    drift^2)`` (the averaged baseline's own noise included), shape (N,).

    Parameters
    ----------
    noise_gray, drift : ndarray, shape (N,), or None
        Each fiber's frame-to-frame noise (gray levels) and drift (relative); None: not measured (0).
    light : ndarray, shape (N,)
        Each fiber's rest light above black, gray levels (> 0).
    """
    e2 = np.zeros(light.shape, dtype=np.float64)
    if noise_gray is not None:
        e2 += np.square(np.asarray(noise_gray, dtype=np.float64) / np.maximum(light, 1.0)) * (
            1.0 + 1.0 / max(baseline_frames, 1))
    if drift is not None:
        e2 += np.square(np.asarray(drift, dtype=np.float64))
    return np.sqrt(e2)


def drift_share(drift: np.ndarray | None, excursion: np.ndarray) -> np.ndarray:
    """The drift's share of each fiber's rest excursion's variance, ``d^2 / e^2`` (0 where ``e`` is 0 or no
    drift was measured), shape (N,)."""
    if drift is None:
        return np.zeros(excursion.shape)
    d2 = np.square(np.asarray(drift, dtype=np.float64))
    e2 = np.square(excursion)
    return np.divide(d2, e2, out=np.zeros(e2.shape), where=e2 > 0)


class FiberModel:
    """A bundle's per-fiber noise (gray levels) and drift (relative), and how many values each is from."""

    def __init__(self, bundle: CalibrationBundle) -> None:
        meta = bundle.extra_meta.get(LEVELS_KEY, {})
        arrays = bundle.extra_arrays
        self.noise: np.ndarray | None = arrays.get(NOISE_KEY)
        self.drift: np.ndarray | None = arrays.get(DRIFT_KEY)
        self.samples = int(meta.get("drift_samples" if self.drift is not None else "noise_samples", 0))
        self.baseline_frames = bundle.baseline_frames
        self.n_fibers = bundle.layout.n_fibers
        #: The noise was measured between snapshots: it is drift too.
        self.noise_is_drift = bool(meta.get("noise_between_snapshots", False))

    @property
    def known(self) -> bool:
        return (self.noise is not None or self.drift is not None) and self.samples >= 2


class ContactLevels:
    """Truncation, off and on levels (float32, signal units), set when the baseline is ready; each fiber's band.

    Parameters
    ----------
    options : ContactOptions
        The switches and the measured noise.
    threshold : float
        The bundle's calibrated threshold (gray levels): all three levels until the baseline is ready.
    fibers : FiberModel, optional
        Each fiber's noise and drift (None, or not known: the levels from ``options.noise_rel``, no bands).
    """

    def __init__(self, options: ContactOptions, threshold: float, fibers: FiberModel | None = None) -> None:
        self.options = options
        self._threshold = float(threshold)
        self.trunc = self.off = self.on = np.float32(threshold)
        #: The MCU's contact-on level, relative units (None: the calibrated one).
        self.on_override: float | None = None
        #: For the gain compensation, relative units: the cluster width (the off level) and the
        #: gain change allowed without evidence.
        self.gain_delta = 0.0
        self.gain_tolerance = 0.0
        #: The truncation level, relative units: a smaller change of the light cannot make a contact.
        self.gain_significant = 0.0
        per_fiber = fibers is not None and fibers.known and options.noise_levels and options.relative
        self._fibers = fibers if per_fiber else None
        #: Each fiber's ``c^2`` and shift, shape (2, N), float32, as the kernel reads them
        #: (:func:`band_rows`; None: no per-fiber model).
        self.bands: np.ndarray | None = None
        if per_fiber and fibers is not None:
            self.bands = band_rows(np.zeros(fibers.n_fibers), np.zeros(fibers.n_fibers), 0.0,
                                   np.zeros((2, fibers.n_fibers), dtype=np.float32))
        #: The widest rest excursion of a fiber once banded, ``e_ref (1 + tol)``, at the last baseline, relative
        #: units (NaN: not per fiber): what the levels are ``k`` times where none was chosen.
        self.noise = math.nan

    def update(self, baseline: np.ndarray, live: np.ndarray) -> None:
        """Set the levels from a ready ``baseline`` (shape (N,)) and the ``live`` fibers (bool, (N,))."""
        o = self.options
        values = baseline[live] if live.any() else baseline
        rest = float(np.median(values)) - o.black_level if values.size else 1.0
        rest = max(rest, 1.0)
        unit = 1.0 if o.relative else rest  # signal units per relative unit
        excess = share = None
        sigma_rel = o.noise_rel
        if self._fibers is not None:
            f = self._fibers
            e = rest_excursion(f.noise, f.drift, np.asarray(baseline, dtype=np.float64) - o.black_level,
                               f.baseline_frames)
            alive = live if live.any() else np.ones(e.shape, dtype=bool)
            self.noise = sigma_rel = float(np.median(e[alive])) * (1.0 + tolerance(f.samples))
            excess = fiber_excess(e, alive, f.samples)
            share = np.ones(e.shape) if f.noise_is_drift else drift_share(f.drift, e)
        if o.noise_levels and o.on_level > 0:  # chosen on held-out presses
            on = max(o.on_level, o.floor_on) * unit
            off = max(on * o.k_off / o.k_on, o.floor_off * unit)
            trunc = max(on * o.k_trunc / o.k_on, o.floor_trunc * unit)
            off, trunc = min(off, on), min(trunc, on)
        elif o.noise_levels:
            sigma = sigma_rel * unit if o.relative or self._fibers is not None else o.noise_gray
            trunc = max(o.k_trunc * sigma, o.floor_trunc * unit)
            off = max(o.k_off * sigma, o.floor_off * unit, trunc)
            on = max(o.k_on * sigma, o.floor_on * unit, off)
        else:
            thr = self._threshold
            trunc = off = on = thr / rest if o.relative else thr
        if self.on_override is not None:  # the MCU's SET_THRESHOLD
            on = self.on_override * unit
            off, trunc = min(off, on), min(trunc, on)
        if not o.hysteresis:
            off = on
        self.trunc, self.off, self.on = np.float32(trunc), np.float32(off), np.float32(on)
        self.gain_delta = float(off) / unit
        self.gain_tolerance = GAIN_TOLERANCE * float(trunc) / unit
        self.gain_significant = float(trunc) / unit
        if self.bands is not None:
            zero = np.zeros(self.bands.shape[1])
            band_rows(zero if excess is None else excess, zero if share is None else share, float(self.on),
                      self.bands)

    @property
    def band(self) -> np.ndarray | None:
        """Where each fiber's signal starts to count, ``b_d + c``, signal units, shape (N,) (0: no band; None:
        no per-fiber model)."""
        return None if self.bands is None else np.sqrt(self.bands[0]) + self.bands[1]

    def as_tuple(self) -> tuple[float, float, float]:
        """(truncation, off, on) as floats."""
        return float(self.trunc), float(self.off), float(self.on)
