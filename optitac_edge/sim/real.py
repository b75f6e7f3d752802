"""The statistics of a real fiber sensor, for the ``real`` physics (issue 37).

Modelled on what a public data set of a real plastic-fiber tactile sensor (61
colour-coded fibers in a hexagon at about 4 mm pitch, a 640 x 480 webcam, a
coloured silicone skin, presses of 1-7 N by a robot arm with a force/torque
sensor, five days, snapshots seconds to minutes apart) showed, as measured:

* each fiber's light **wanders**: between rest frames minutes apart it moved by
  a median 2.0 %, 90th percentile 5.9 %, maximum 12.3 %, the outer ring the
  noisiest; here a random walk per fiber (:class:`FiberWander`), its five-minute
  spread 2.5 % inside, 6 % on the outer ring, three times that on one fiber in
  twenty (over five minutes: median 2.3 %, 90th percentile 6.6 %, max 12-20 %
  across the 61 fibers);
* one fiber **brightened 39 %** within a 30-minute session: here one fiber, from
  ten minutes into a session, over the next thirty;
* between **days** some fibers differ by up to about 30 %: here each fiber's
  light times ``1 + N(0, 0.12)`` clipped to +-30 %, drawn per day (day 0: none);
* **colour-coded** fibers under a coloured skin: each fiber has a tint, and a
  press shifts the chromaticity of the fibers it darkens (the chromaticity change
  alone told contact frames from rest frames about as well as the luma);
* **stray light**: four dim blobs in the image corners, 2-3 gray levels over an
  18 background (they made the fiber map refuse);
* the **geometry**: 61 fibers at 4 mm, end faces a third of a pitch across
  (16 px at 50 px), a dim, uneven fiber light (45-200 gray).

The recordings of the real data set were snapshots; the ``snapshots`` scenario
makes such sessions (:mod:`optitac_edge.sim.scenarios`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from optitac_edge.core.layout import FiberLayout

#: The real sensor's array: rings and pitch, mm.
REAL_RINGS, REAL_PITCH_MM = 4, 4.0
#: Its camera (a webcam): the optics' fields the ``real`` physics sets.
REAL_OPTICS = {
    "fiber_diameter_mm": 1.3, "background_gray": 18.0, "led_peak_gray": 125.0, "transmission_sigma": 0.3,
    "vignetting": 0.1, "noise_sigma": 1.5, "row_noise_sigma": 0.3, "fill_fraction": 0.83,
    "stray_light": ((22.0, 22.0, 8.0, 2.5), (618.0, 24.0, 7.0, 2.0), (24.0, 456.0, 8.0, 3.0),
                    (615.0, 458.0, 7.0, 2.5)),
}


@dataclass(frozen=True)
class FiberWander:
    """How each fiber's light wanders, relative to it.

    Attributes
    ----------
    five_min : float
        Standard deviation of a fiber's random walk over five minutes, inner fibers.
    five_min_outer : float
        The same, fibers of the outer ring.
    wild_fraction, wild_factor : float
        This fraction of the fibers wanders this many times as much.
    jump : float
        One fiber brightens by this much (relative) ...
    jump_start_s, jump_s : float
        ... from this time into a session, over this long.
    day_sigma, day_limit : float
        Each fiber's light between days: times ``1 + N(0, day_sigma)`` clipped to +-``day_limit``.
    """

    five_min: float = 0.025
    five_min_outer: float = 0.06
    wild_fraction: float = 0.05
    wild_factor: float = 3.0
    jump: float = 0.39
    jump_start_s: float = 600.0
    jump_s: float = 1800.0
    day_sigma: float = 0.12
    day_limit: float = 0.3

    def scales(self, layout: FiberLayout, rng: np.random.Generator) -> np.ndarray:
        """Each fiber's five-minute spread, shape (N,)."""
        r = np.hypot(layout.xy_mm[:, 0], layout.xy_mm[:, 1])
        outer = r > r.max() - 0.5 * layout.pitch_mm
        s = np.where(outer, self.five_min_outer, self.five_min)
        wild = rng.random(layout.n_fibers) < self.wild_fraction
        return np.where(wild, s * self.wild_factor, s)


class WanderingLight:
    """Each fiber's light factor over a session's time: the day's gain, a random walk, one fiber's jump.

    Deterministic for its seeds, for times asked in any order (the walk is drawn on a one-second grid as far
    as asked, and interpolated).

    Parameters
    ----------
    layout : FiberLayout
    wander : FiberWander
    sensor_seed, day, session_seed : int
        The physical sensor (which fibers are wild, which one jumps), the day (its gains; 0: none) and the
        session (its walk).
    """

    def __init__(self, layout: FiberLayout, wander: FiberWander, sensor_seed: int, day: int,
                 session_seed: int) -> None:
        self._w = wander
        sensor_rng = np.random.default_rng([sensor_seed, 37])
        n = layout.n_fibers
        self._step = wander.scales(layout, sensor_rng) / math.sqrt(300.0)  # per sqrt(s)
        self._jumper = int(sensor_rng.integers(n))
        day_rng = np.random.default_rng([sensor_seed, day, 38])
        gain = np.clip(1.0 + wander.day_sigma * day_rng.standard_normal(n), 1 - wander.day_limit,
                       1 + wander.day_limit)
        self.day_gain = np.ones(n) if day == 0 else gain
        self._rng = np.random.default_rng([sensor_seed, day, session_seed, 39])
        self._walk = np.zeros((1, n))  # the walk at 0, 1, 2, ... s

    def _extend(self, seconds: int) -> None:
        have = self._walk.shape[0]
        if seconds < have:
            return
        steps = self._rng.standard_normal((seconds + 1 - have, self._step.size)) * self._step
        self._walk = np.concatenate([self._walk, self._walk[-1] + np.cumsum(steps, axis=0)])

    def factor(self, t_s: float) -> np.ndarray:
        """Each fiber's light factor at ``t_s`` s into the session, shape (N,)."""
        t = max(float(t_s), 0.0)
        k = math.floor(t)
        self._extend(k + 1)
        f = t - k
        walk = (1.0 - f) * self._walk[k] + f * self._walk[k + 1]
        out = self.day_gain * np.exp(walk)
        w = self._w
        out[self._jumper] *= 1.0 + w.jump * min(max((t - w.jump_start_s) / w.jump_s, 0.0), 1.0)
        return out


@dataclass(frozen=True)
class FiberColours:
    """Colour-coded fibers under a coloured skin: each fiber's tint, and the chromaticity a press gives.

    The light of fiber ``i`` darkened by ``d`` is ``(1 - d) (tint_i + d * shift_i)`` per channel: the shift
    sums to 0 over the channels' luma weights (a press changes the colour, not by itself the luma).
    """

    tints: np.ndarray  # (N, 3)
    shifts: np.ndarray  # (N, 3)

    @classmethod
    def draw(cls, n_fibers: int, sensor_seed: int) -> FiberColours:
        """A palette of tints as the real sensor's (mostly white, some rose, some yellow) and per-fiber shifts
        towards the skin's pigment."""
        rng = np.random.default_rng([sensor_seed, 40])
        palette = np.array([[1.0, 1.0, 1.0], [1.0, 0.82, 0.9], [1.0, 0.97, 0.78], [0.92, 1.0, 0.95]])
        tints = palette[rng.choice(len(palette), n_fibers, p=[0.55, 0.2, 0.15, 0.1])]
        luma = np.array([0.299, 0.587, 0.114])
        pigment = np.array([0.35, -0.25, 0.45]) * (1.0 + 0.3 * rng.standard_normal((n_fibers, 1)))
        shifts = pigment - (pigment @ luma)[:, None]  # no luma of its own
        return cls(tints=tints, shifts=shifts)

    def rgb(self, darkening: np.ndarray) -> np.ndarray:
        """Each fiber's channel gains at ``darkening`` (shape (N,)), shape (N, 3), before the ``(1 - d)``."""
        return self.tints + np.clip(np.asarray(darkening), 0.0, 1.0)[:, None] * self.shifts
