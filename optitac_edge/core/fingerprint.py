"""A bundle's sensor, told from its frames: do the fibers light where the bundle's fiber map puts them?

A bundle fits a camera's frames when the frames have its size and pixel format
(:meth:`~optitac_edge.core.fiber_table.FiberTable.check_frame_shape`) *and* its
fibers light where its map puts them. The second is measured by each live
fiber's **contrast** in the mean of a few contact-free frames:

    contrast_i = (light at the fiber's centre - light between it and its layout neighbours)
                 / (light at the fiber's centre - black level)

(the light between two fibers is the median over the midpoints of the image
segments to its neighbours). On the sensor the bundle was made for the centre
is bright and the gaps are dark: contrast near 1 (0.99 on the simulator,
lower where spots touch). On another sensor, or a moved camera, the map's
centres and gaps fall anywhere on the image: a 61-fiber bundle's map on the
built-in 217-fiber camera puts its centres on fibers *and* its gaps on fibers
(the 61-fiber lattice is a sub-lattice of the 217-fiber one), contrast near 0.

The bundle keeps its own contrast, measured on its rest frames at calibration
(:func:`fingerprint_meta`, in ``extra_meta["sensor"]`` with the layout's size,
pitch and a digest of its ids and positions, and the frame geometry). A fiber
*fits* when its contrast is at least :data:`FIT_SHARE` of the bundle's; the
frames fit when at least :data:`MIN_FIT_FRACTION` of the live fibers do. A
press darkens fibers but leaves their gaps dark: the contrast of a pressed
fiber stays high, so a press at start does not refuse a bundle.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from optitac_edge.core.frames import to_gray
from optitac_edge.errors import FrameMismatchError

if TYPE_CHECKING:
    from optitac_edge.core.bundle import CalibrationBundle
    from optitac_edge.core.fiber_table import FiberTable
    from optitac_edge.core.layout import FiberLayout

#: The key of a bundle's ``extra_meta`` that holds its sensor's fingerprint.
FINGERPRINT_KEY = "sensor"
#: A fiber fits when its contrast is at least this share of the bundle's own (its median at calibration).
FIT_SHARE = 0.5
#: A bundle without a fingerprint (written before it was kept) is judged against this contrast.
DEFAULT_CONTRAST = 0.5
#: The frames fit the bundle when at least this fraction of its live fibers fit. A bundle on its own sensor:
#: 1.00 on every simulated physics; on another sensor or a moved camera: 0.00-0.10 (docs/formats.md).
MIN_FIT_FRACTION = 0.5
#: Pixels the black level is read at: this low percentile of the mean frame.
BLACK_PERCENTILE = 5.0


class SensorMismatchError(FrameMismatchError):
    """The frames are not of the sensor a bundle was made for (another sensor, a moved camera)."""


@dataclass(frozen=True)
class SensorFit:
    """How well frames fit a bundle's fiber map.

    Attributes
    ----------
    fitting, live : int
        Live fibers whose contrast fits, and live fibers (n of the figure).
    contrast : float
        Median contrast of the live fibers in these frames.
    expected : float
        The bundle's own contrast (at calibration; :data:`DEFAULT_CONTRAST` for a bundle without one).
    frames : int
        Frames averaged.
    """

    fitting: int
    live: int
    contrast: float
    expected: float
    frames: int

    @property
    def fraction(self) -> float:
        return self.fitting / self.live if self.live else 0.0

    @property
    def fits(self) -> bool:
        return self.live > 0 and self.fraction >= MIN_FIT_FRACTION

    def __str__(self) -> str:
        return (f"{self.fitting} of {self.live} fibers light where its map puts them (contrast {self.contrast:.2f}; "
                f"the bundle's own {self.expected:.2f}; {self.frames} frames)")


def layout_digest(layout: FiberLayout) -> str:
    """16 hex digits of SHA-256 over the layout's ids and positions (rounded to 1 µm)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(layout.ids, dtype="<i8").tobytes())
    h.update(np.ascontiguousarray(np.rint(layout.xy_mm * 1000.0), dtype="<i8").tobytes())
    return h.hexdigest()[:16]


def gap_points(table: FiberTable, layout: FiberLayout) -> tuple[np.ndarray, np.ndarray]:
    """The image points between each fiber and its layout neighbours (the midpoints of the segments joining
    their centres, px), and which fiber each belongs to.

    Returns
    -------
    points : ndarray, shape (M, 2), float64
        (col, row) of each midpoint.
    owner : ndarray, shape (M,), intp
        The fiber (layout index) whose gap it is.
    """
    pairs = layout.neighbour_pairs()
    c = table.centroid_px
    points = 0.5 * (c[pairs[:, 0]] + c[pairs[:, 1]])
    # each pair is the gap of both its fibers
    return np.concatenate([points, points]), np.concatenate([pairs[:, 0], pairs[:, 1]]).astype(np.intp)


def _sample(gray: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``gray`` at the nearest pixel of each (col, row) point (clipped to the image)."""
    col = np.clip(np.rint(points[:, 0]), 0, gray.shape[1] - 1).astype(np.intp)
    row = np.clip(np.rint(points[:, 1]), 0, gray.shape[0] - 1).astype(np.intp)
    return gray[row, col].astype(np.float64)


def fiber_contrast(mean_gray: np.ndarray, table: FiberTable, layout: FiberLayout) -> np.ndarray:
    """Each fiber's contrast in a mean gray frame (see the module's docstring), shape (N,), float64;
    NaN for a fiber without a neighbour."""
    n = table.n_fibers
    spot = _sample(mean_gray, table.centroid_px)
    points, owner = gap_points(table, layout)
    gap_light = _sample(mean_gray, points)
    gap = np.full(n, np.nan)
    if owner.size:
        order = np.argsort(owner, kind="stable")
        owner, gap_light = owner[order], gap_light[order]
        starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
        for s, e in zip(starts, np.r_[starts[1:], owner.size]):
            gap[owner[s]] = float(np.median(gap_light[s:e]))
    black = float(np.percentile(mean_gray, BLACK_PERCENTILE))
    return (spot - gap) / np.maximum(spot - black, 1.0)


def fingerprint_meta(bundle: CalibrationBundle, rest_frames: Iterable[np.ndarray] | np.ndarray) -> dict[str, Any]:
    """The sensor's fingerprint a bundle keeps (``extra_meta["sensor"]``): the layout (fibers, pitch,
    digest), the frames (size, pixel format) and the contrast of its live fibers in ``rest_frames``."""
    t = bundle.fibers
    fit = sensor_fit(bundle, rest_frames, t.pixel_format)
    return {"n_fibers": bundle.layout.n_fibers, "pitch_mm": round(bundle.layout.pitch_mm, 6),
            "layout": layout_digest(bundle.layout), "width": t.width, "height": t.height,
            "pixel_format": t.pixel_format, "contrast": round(fit.contrast, 4) if fit.live else DEFAULT_CONTRAST}


def expected_contrast(bundle: CalibrationBundle) -> float:
    """The bundle's own contrast, or :data:`DEFAULT_CONTRAST` for a bundle without a fingerprint."""
    meta = bundle.extra_meta.get(FINGERPRINT_KEY)
    value = meta.get("contrast") if isinstance(meta, dict) else None
    if isinstance(value, (int, float)) and not isinstance(value, bool) and 0.0 < value <= 2.0:
        return float(value)
    return DEFAULT_CONTRAST


def sensor_fit(bundle: CalibrationBundle, frames: Iterable[np.ndarray] | np.ndarray, pixel_format: str) -> SensorFit:
    """How well ``frames`` (contact-free, or mostly so; of the bundle's size) fit ``bundle``'s fiber map."""
    check = SensorCheck(bundle, pixel_format=pixel_format)
    for frame in frames:
        check.add(np.asarray(frame))
    return check.fit()


def describe_bundle(bundle: CalibrationBundle) -> str:
    """A bundle as a person names it: its file (or id), fibers and frames."""
    t = bundle.fibers
    name = bundle.source or f"bundle {bundle.calibration_id or '(unsaved)'}"
    return f"{name} ({bundle.layout.n_fibers} fibers, {t.width}x{t.height} {t.pixel_format})"


def check_sensor(bundle: CalibrationBundle, frames: Sequence[np.ndarray] | np.ndarray, pixel_format: str,
                 source: str) -> SensorFit:
    """Raise :class:`SensorMismatchError` unless ``frames`` of ``source`` (a recording, a camera) are of the
    sensor ``bundle`` was made for: their size and pixel format, then where its fibers light."""
    if len(frames) == 0:
        raise FrameMismatchError(f"{source}: no frames to check against {describe_bundle(bundle)}")
    try:
        bundle.fibers.check_frame(np.asarray(frames[0]), pixel_format)
    except FrameMismatchError as exc:
        raise SensorMismatchError(f"{source} does not fit {describe_bundle(bundle)}: {exc}") from None
    check = SensorCheck(bundle, source, pixel_format)
    for frame in frames:
        check.add(np.asarray(frame))
    return check.finish()


class SensorCheck:
    """:func:`check_sensor` on the first frames a pipeline takes as its baseline, one frame at a time.

    Parameters
    ----------
    bundle : CalibrationBundle
    source : str
        What the frames come from, for the error's line (``"the camera's frames"``).
    pixel_format : str, optional
        The frames' (default: the bundle's).
    """

    def __init__(self, bundle: CalibrationBundle, source: str = "the frames", pixel_format: str | None = None) -> None:
        self.bundle = bundle
        self.source = source
        self._format = bundle.fibers.pixel_format if pixel_format is None else pixel_format
        self._total: np.ndarray | None = None
        self._frames = 0

    def add(self, frame: np.ndarray) -> None:
        """One more frame (of the bundle's size and pixel format: the pipeline checked it)."""
        g = to_gray(frame, self._format)
        if self._total is None:
            self._total = np.zeros(g.shape, dtype=np.float64)
        self._total += g
        self._frames += 1

    def fit(self) -> SensorFit:
        """How the frames added so far fit the bundle's fiber map."""
        if self._total is None:
            raise FrameMismatchError(f"{self.source}: no frames to check against {describe_bundle(self.bundle)}")
        return _fit(self.bundle, self._total / self._frames, self._frames)

    def finish(self) -> SensorFit:
        """:meth:`fit`, the sums released; :class:`SensorMismatchError` when the frames do not fit."""
        fit = self.fit()
        self._total, self._frames = None, 0
        if not fit.fits:
            raise SensorMismatchError(_mismatch_line(self.source, self.bundle, fit))
        return fit


def _fit(bundle: CalibrationBundle, gray: np.ndarray, frames: int) -> SensorFit:
    t = bundle.fibers
    contrast = fiber_contrast(gray, t, bundle.layout)
    live = ~t.dead & np.isfinite(contrast)
    expected = expected_contrast(bundle)
    c = contrast[live]
    return SensorFit(fitting=int(np.count_nonzero(c >= FIT_SHARE * expected)), live=int(live.sum()),
                     contrast=float(np.median(c)) if c.size else 0.0, expected=expected, frames=frames)


def _mismatch_line(source: str, bundle: CalibrationBundle, fit: SensorFit) -> str:
    return (f"{source} are not of the sensor of {describe_bundle(bundle)}: {fit}; another sensor or a moved "
            f"camera: calibrate the fibers on this sensor's rest frames (calibrate fibers)")
