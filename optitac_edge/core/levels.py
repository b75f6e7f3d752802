"""The contact levels in signal units: truncation, contact off and contact on.

The paper truncates the surface at one calibrated threshold. With
``noise_levels`` the three levels are ``k`` times the noise measured at
calibration (each at least a floor fraction of the rest light); with
``hysteresis`` a contact ends at the lower off level. The MCU's
SET_THRESHOLD overrides the on level (relative units of the rest light).
"""

from __future__ import annotations

import numpy as np

from optitac_edge.core.options import ContactOptions

#: compensate_gain: the LED gain of a frame with contact may differ from the last contact-free
#: frame's by this many truncation levels (plus ``gain_rate_per_s`` times the time since).
GAIN_TOLERANCE = 0.1


class ContactLevels:
    """Truncation, off and on levels (float32, signal units), set when the baseline is ready.

    Parameters
    ----------
    options : ContactOptions
        The switches and the measured noise.
    threshold : float
        The bundle's calibrated threshold (gray levels): all three levels until the baseline is ready.
    """

    def __init__(self, options: ContactOptions, threshold: float) -> None:
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

    def update(self, baseline: np.ndarray, live: np.ndarray) -> None:
        """Set the levels from a ready ``baseline`` (shape (N,)) and the ``live`` fibers (bool, (N,))."""
        o = self.options
        values = baseline[live] if live.any() else baseline
        rest = float(np.median(values)) - o.black_level if values.size else 1.0
        rest = max(rest, 1.0)
        unit = 1.0 if o.relative else rest  # signal units per relative unit
        if o.noise_levels:
            sigma = o.noise_rel if o.relative else o.noise_gray
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

    def as_tuple(self) -> tuple[float, float, float]:
        """(truncation, off, on) as floats."""
        return float(self.trunc), float(self.off), float(self.on)
