"""Orientation without a rig: the user presses near the sensor's +x edge, then near its +y edge.

A pure state machine fed one contact estimate per frame (no I/O, no clock of
its own); the ``orient`` command and the live view drive it and show its
:attr:`EdgePresses.prompt`. Two presses near marked edges are enough: the
layout's symmetries put ``+x`` and ``+y`` at 60-degree steps, so a press
anywhere within about 25 degrees of the edge's direction picks one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from optitac_edge.calibration.orientation import OrientationFit, Symmetry, fit_orientation, layout_symmetries
from optitac_edge.core.layout import FiberLayout

#: Where the two presses are expected, as a fraction of the array radius along +x and +y.
EDGE_FRACTION = 0.7
#: A press is taken once held this long with its centroid within ``STILL_PITCH`` pitches (1 mm on the
#: paper's 1.5 mm array), s.
HOLD_S = 0.6
STILL_PITCH = 1.0 / 1.5
#: Then the skin must be released for this long, s.
RELEASE_S = 0.3
#: A press nearer the centre than this fraction of the radius cannot tell directions apart.
MIN_RADIUS_FRACTION = 0.35


@dataclass
class EdgePresses:
    """Guided orientation: press near +x, release, press near +y, release -> the layout symmetry.

    Parameters
    ----------
    layout : FiberLayout
        The bundle's layout (its symmetries are the candidates).

    Attributes
    ----------
    prompt : str
        What the user should do now.
    fit : OrientationFit or None
        Set when both presses were taken; ``fit.symmetry`` is None when they
        did not decide (``fit.reason`` says why; :meth:`restart` to try again).
    """

    layout: FiberLayout
    prompt: str = ""
    fit: OrientationFit | None = None
    taken: list[tuple[float, float]] = field(default_factory=list)
    _held: list[tuple[int, float, float]] = field(default_factory=list)
    _released_ns: int | None = None
    _waiting_release: bool = False

    def __post_init__(self) -> None:
        self.restart()

    @property
    def targets_mm(self) -> np.ndarray:
        """The nominal press positions (+x edge, +y edge), shape (2, 2), mm."""
        r = EDGE_FRACTION * self.layout.radius_mm
        return np.array([[r, 0.0], [0.0, r]])

    @property
    def done(self) -> bool:
        return self.fit is not None

    def restart(self) -> None:
        """Start again from the first press."""
        self.taken, self._held, self.fit = [], [], None
        self._waiting_release, self._released_ns = False, None
        self.prompt = "press near the +x edge (marked on the housing) and hold still"

    def feed(self, contact: bool, x_mm: float, y_mm: float, t_ns: int) -> None:
        """One frame's primary contact (``contact`` False: none) at time ``t_ns``, ns."""
        if self.fit is not None:
            return
        if self._waiting_release:
            if contact:
                self._released_ns = None
            elif self._released_ns is None:
                self._released_ns = t_ns
            elif t_ns - self._released_ns >= RELEASE_S * 1e9:
                self._waiting_release = False
                self._next()
            return
        if not contact or not (math.isfinite(x_mm) and math.isfinite(y_mm)):
            self._held = []
            return
        self._held.append((t_ns, x_mm, y_mm))
        xy = np.array([(x, y) for _, x, y in self._held])
        if np.max(np.hypot(*(xy - xy.mean(axis=0)).T)) > STILL_PITCH * self.layout.pitch_mm:
            self._held = self._held[-1:]  # moved: start the hold again from here
            return
        if t_ns - self._held[0][0] < HOLD_S * 1e9:
            return
        cx, cy = (float(v) for v in xy.mean(axis=0))
        self._held = []
        self._waiting_release = True
        if math.hypot(cx, cy) < MIN_RADIUS_FRACTION * self.layout.radius_mm:
            self.prompt = "that press was too near the centre: release, then press nearer the edge"
            return
        self.taken.append((cx, cy))
        self.prompt = "release"

    def _next(self) -> None:
        if len(self.taken) == 1:
            self.prompt = "press near the +y edge (90° counter-clockwise from +x) and hold still"
        elif len(self.taken) == 2:
            self.fit = resolve_edge_presses(np.array(self.taken), self.layout)
            self.prompt = (f"done: the fiber map is {self.fit.symmetry.label}" if self.fit.symmetry is not None
                           else f"not decided: {self.fit.reason}")
        else:
            self.prompt = "press near the +x edge (marked on the housing) and hold still"


def resolve_edge_presses(measured_mm: np.ndarray, layout: FiberLayout,
                         symmetries: list[Symmetry] | None = None) -> OrientationFit:
    """The symmetry ``h`` with the two presses (+x edge, +y edge) read at ``h`` of their nominal places.

    Parameters
    ----------
    measured_mm : ndarray, shape (2, 2)
        Mean centroids of the +x and +y presses, read through the bundle, mm.
    """
    r = EDGE_FRACTION * layout.radius_mm
    targets = np.array([[r, 0.0], [0.0, r]])
    return fit_orientation(measured_mm, targets, symmetries or layout_symmetries(layout), layout.pitch_mm,
                           accept_mm=0.45 * r, margin_mm=0.1 * r, margin_ratio=1.3)
