"""How the per-frame method decides what is a contact: thresholds and the improvements beyond the paper.

Both are stored in the calibration bundle's meta (see bundle.py and docs/formats.md).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

from optitac_edge.core.colour import COLOUR_MIXES

#: Most simultaneous contacts the pipeline reports.
MAX_CONTACTS = 4
#: Smallest contact area, square pitches (1 mm2 on the paper's 1.5 mm array).
MIN_AREA_PITCH2 = 1.0 / 1.5**2


def _require_non_negative(obj: Any, names: tuple[str, ...]) -> None:
    """Raise ValueError naming the first of ``obj``'s fields ``names`` that is not a finite number >= 0."""
    for name in names:
        v = getattr(obj, name)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")


@dataclass(frozen=True)
class ContactThresholds:
    """When the surface counts as a contact.

    Attributes
    ----------
    threshold : float
        Gray levels. The inverted, baseline-subtracted surface is truncated
        below this value (kept as it is above it).
    min_area_mm2 : float
        Minimum area above the threshold for a contact to be reported.
    """

    threshold: float = 6.0
    min_area_mm2: float = 1.0

    def __post_init__(self) -> None:
        _require_non_negative(self, ("threshold", "min_area_mm2"))

    @classmethod
    def for_pitch(cls, pitch_mm: float) -> ContactThresholds:
        """The defaults for an array of this pitch: the smallest contact :data:`MIN_AREA_PITCH2` square pitches."""
        return cls(min_area_mm2=MIN_AREA_PITCH2 * pitch_mm * pitch_mm)


@dataclass(frozen=True)
class ContactOptions:
    """Improvements beyond the paper's per-frame method, each switchable.

    Stored in the bundle's meta under ``contact_options`` (strictly validated:
    an unknown key or a bad value is a :class:`BundleError` naming the key).
    :meth:`paper` switches everything off: the pipeline then does exactly the
    paper's method with :class:`ContactThresholds` (and agrees with
    :class:`~optitac_edge.devtools.reference.ReferencePipeline`). A bundle file without
    ``contact_options`` (written before they existed) loads as :meth:`paper`.

    Signal units: gray levels, or relative units (fraction of the fiber's rest
    light above the black level) when ``relative`` is set. The *levels* below
    (truncation, off, on) are in those units.

    Attributes
    ----------
    relative : bool
        Per-fiber signal ``(baseline - mean) / (baseline - black_level)``:
        removes the fibers' transmission spread and LED vignetting, and makes
        the signal invariant to the overall brightness. The paper threshold
        (when ``noise_levels`` is off) is converted with the median rest level.
    noise_levels : bool
        Truncation / off / on levels from the data: ``on_level`` where
        ``calibrate levels`` chose it on held-out presses (the others in the
        ``k`` ratios), else ``max(k * noise, floor)`` of the rest-frame noise
        measured at calibration (``noise_rel`` or ``noise_gray``); and each
        fiber's band from its own rest excursion
        (:mod:`optitac_edge.core.levels`). Off: the paper's single
        ``ContactThresholds.threshold`` for all three.
    hysteresis : bool
        A contact starts when a blob's peak exceeds the *on* level and stays
        while it exceeds the lower *off* level. Off: the on level for both.
    peak_fraction : float
        Each contact is truncated at ``max(truncation level, peak_fraction *
        its peak)``: widths and centroid then do not depend on the signal
        amplitude. 0 switches it off (truncation level only).
    shape_fraction : float
        The shape features (Hu, q4) are taken from the contact binarized at
        ``max(truncation level, shape_fraction * its peak)``. 0: the same
        cells as the moments (the paper: the truncated surface).
    fill_dead : bool
        Dead fibers take the (harmonic) mean of their neighbours, folded into
        the interpolation matrix (``A' = A F``, no per-frame cost). Off: 0.
    max_contacts : int
        1..4. More than 1: separate blobs (8-connected) of the surface above
        ``max(truncation level, split_fraction * the strongest peak)`` are
        separate contacts, strongest ``m00`` first. 1: the whole surface
        above the truncation level is one contact (the paper).
    split_fraction : float
        See ``max_contacts`` (the skin's spread joins nearby presses at the
        noise level, so blobs are separated higher up).
    track_baseline : bool
        Exponential moving average of the fiber means (time constant
        ``baseline_tau_s`` from the frame timestamps) while there is no
        contact, no contact ended in the last ``holdoff_s`` seconds and no
        fiber's signal departs from the median fiber signal by the off level
        or more (a uniform drift is tracked, a local press is not).
    compensate_gain : bool
        Common-mode LED gain compensation: every frame the fiber light above
        the black level is divided by the frame's LED gain relative to the
        baseline, ``g``, before the signal, so an LED dimming during a
        recording is not a press. ``g`` is the median ratio ``(mean -
        black_level) / (baseline - black_level)`` of the fibers within the off
        level of the brightest-relative cluster (contacts only darken
        fibers), limited to the gain of the last contact-free frame
        ``+- (truncation level / 10 + gain_rate_per_s * seconds since)``: a
        press covering the whole array cannot be taken for a dimming (its
        gain is held), and a contact that drift started ends when the limit
        has grown to the drift. The baseline tracking then follows the
        gain-compensated means (per-fiber drift only).
    gain_rate_per_s : float
        Fastest LED gain change (relative, per second) followed during a contact.
    k_trunc, k_off, k_on : float
        Levels in units of the measured noise.
    floor_trunc, floor_off, floor_on : float
        Lower bounds of the levels, relative units (converted to gray levels
        with the median rest level when ``relative`` is off).
    gap_s : float
        Frames further apart than this (s, the frames' own times) are independent snapshots (a labelled
        data set, a rig that photographs each press, a camera that stalled): nothing is carried across
        the gap -- no hysteresis, motion, vibration filter, baseline tracking step, bright-fiber timer, and
        no contact id (every contact before it is released, every contact after it touches anew). The
        baseline itself is kept (a tare retakes it).
    baseline_tau_s, holdoff_s : float
        See ``track_baseline``. The holdoff defaults to 0: the quiet-frame check
        already keeps a press's residue out of the baseline, and with presses in
        quick succession (a rest frame or two between them) any holdoff stops
        the tracking, so per-fiber drift accumulates (then, with the LED gain
        compensated, it alone can hold a contact on through a rest frame).
    colour_mix : str
        RGB frames: the mix of the three channels each fiber's light is read
        through (:data:`~optitac_edge.core.colour.COLOUR_MIXES`; ``luma``,
        BT.601, unless ``calibrate levels`` found on held-out presses that
        another tells contact from rest frames better: the relative change of
        a mix is the luma's plus a chromaticity change).
    support : bool
        Each fiber's signal limited to its second-strongest neighbour's
        (:mod:`optitac_edge.core.support`): a fiber that darkens alone makes
        no contact. Adopted by ``calibrate levels`` only where held-out presses
        show it helps (off by default).
    on_level : float
        Chosen by ``calibrate levels`` on held-out presses of the user's own
        recordings (relative units; 0: not chosen, the levels come from
        ``noise_rel``).
    noise_rel, noise_gray : float
        Measured by calibration: the typical (median) live fiber's
        frame-to-frame noise in the rest frames (times the averaged baseline's
        own noise factor), relative units and gray levels; 0 if unknown (then
        only the floors apply). Fibers noisier than that get bands of their own.
    black_level : float
        Measured by calibration: gray level of the image between the fibers
        (median), subtracted from the baseline in the relative signal.
    """

    relative: bool = True
    noise_levels: bool = True
    hysteresis: bool = True
    peak_fraction: float = 0.4
    shape_fraction: float = 0.3
    split_fraction: float = 0.5
    fill_dead: bool = True
    max_contacts: int = 4
    track_baseline: bool = True
    compensate_gain: bool = True
    k_trunc: float = 4.0
    k_off: float = 6.0
    k_on: float = 10.0
    floor_trunc: float = 0.004
    floor_off: float = 0.006
    floor_on: float = 0.01
    baseline_tau_s: float = 1.0
    holdoff_s: float = 0.0
    gain_rate_per_s: float = 0.005
    gap_s: float = 0.5
    colour_mix: str = "luma"
    support: bool = False
    on_level: float = 0.0
    noise_rel: float = 0.0
    noise_gray: float = 0.0
    black_level: float = 0.0

    #: Switches (``paper()`` turns them off).
    SWITCHES = ("relative", "noise_levels", "hysteresis", "peak_fraction", "shape_fraction", "fill_dead",
                "max_contacts", "track_baseline", "compensate_gain")

    def __post_init__(self) -> None:
        for name in ("relative", "noise_levels", "hysteresis", "fill_dead", "track_baseline",
                     "compensate_gain", "support"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"{name} must be true or false, got {getattr(self, name)!r}")
        mc = self.max_contacts
        if isinstance(mc, bool) or not isinstance(mc, int) or not 1 <= mc <= MAX_CONTACTS:
            raise ValueError(f"max_contacts must be an integer 1..{MAX_CONTACTS}, got {mc!r}")
        _require_non_negative(self, ("peak_fraction", "shape_fraction", "split_fraction", "k_trunc", "k_off",
                                     "k_on", "floor_trunc", "floor_off", "floor_on", "baseline_tau_s",
                                     "holdoff_s", "gain_rate_per_s", "noise_rel", "noise_gray",
                                     "black_level", "gap_s", "on_level"))
        for name in ("peak_fraction", "shape_fraction", "split_fraction"):
            if not getattr(self, name) < 1.0:
                raise ValueError(f"{name} must be < 1, got {getattr(self, name)!r}")
        if not self.black_level < 255.0:  # an 8-bit camera's white: every frame a contact above it
            raise ValueError(f"black_level must be below 255 (gray levels), got {self.black_level!r}")
        if not self.noise_gray <= 255.0:
            raise ValueError(f"noise_gray must be at most 255 (gray levels), got {self.noise_gray!r}")
        for name in ("noise_rel", "on_level"):  # fractions of a fiber's rest light
            if not getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be at most 1 (a fraction of the rest light), got "
                                 f"{getattr(self, name)!r}")
        if self.baseline_tau_s <= 0:
            raise ValueError(f"baseline_tau_s must be > 0, got {self.baseline_tau_s!r}")
        if self.gap_s <= 0:
            raise ValueError(f"gap_s must be > 0, got {self.gap_s!r}")
        if self.colour_mix not in COLOUR_MIXES:
            raise ValueError(f"colour_mix must be one of {', '.join(COLOUR_MIXES)}, got {self.colour_mix!r}")

    @classmethod
    def paper(cls, **measured: Any) -> ContactOptions:
        """All improvements off: the paper's method (measured values may be kept)."""
        return cls(relative=False, noise_levels=False, hysteresis=False, peak_fraction=0.0, shape_fraction=0.0,
                   fill_dead=False, max_contacts=1, track_baseline=False, compensate_gain=False,
                   **measured)

    @property
    def is_paper(self) -> bool:
        p = ContactOptions.paper()
        return all(getattr(self, k) == getattr(p, k) for k in self.SWITCHES)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> ContactOptions:
        """Strict: unknown keys and bad values raise ``ValueError`` naming the key."""
        if not isinstance(d, Mapping):
            raise TypeError("contact_options must be an object")
        known = {f.name for f in fields(cls)}
        for key in d:
            if key not in known:
                raise ValueError(f"unknown contact option {key!r}")
        values = dict(d)
        for key in ("peak_fraction", "shape_fraction", "split_fraction", "k_trunc", "k_off", "k_on", "floor_trunc", "floor_off",
                    "floor_on", "baseline_tau_s", "holdoff_s", "gain_rate_per_s", "noise_rel",
                    "noise_gray", "black_level", "gap_s", "on_level"):
            if key in values and isinstance(values[key], int) and not isinstance(values[key], bool):
                values[key] = float(values[key])
        return cls(**values)
