"""A simulated OptiTac sensor: indenters in, camera frames out, with ground truth."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from optitac_edge.core.layout import FiberLayout, hex_layout
from optitac_edge.sim.drift import NO_DRIFT, SessionDrift
from optitac_edge.sim.optics import DEFAULT_OPTICS, CameraOptics
from optitac_edge.sim.real import FiberColours, WanderingLight
from optitac_edge.sim.render import SENSOR_SEED, FrameRenderer
from optitac_edge.sim.skin import DEFAULT_SKIN, Indenter, SkinModel, fiber_darkening


class SimulatedSensor:
    """Skin model plus camera: renders the frame a real sensor would deliver.

    Parameters
    ----------
    layout : FiberLayout or None
        Fiber layout; None (default): :func:`optitac_edge.core.layout.hex_layout` (217 fibers).
    optics : CameraOptics
        Camera, lens and illumination (default ``CameraOptics()``).
    skin : SkinModel
        Skin response (default ``SkinModel()``).
    seed : int
        Seed of the temporal noise (default 0): differs between recordings.
    sensor_seed : int
        Seed of the physical sensor (fiber transmission spread, fixed-pattern
        noise); default :data:`~optitac_edge.sim.render.SENSOR_SEED`, so every
        simulated sensor is the same physical one unless asked otherwise.
    drift : SessionDrift
        The session ("day") the sensor is used on (default: nominal, no drift).
        The camera shift moves the rendered array exactly; LED gain and drift,
        per-fiber drift, pin gain and per-press depth jitter apply in
        :meth:`darkening` and :meth:`frame_from_darkening`.
    fps : float
        Frame rate (default 60): frame k is at ``t = k / fps`` for the
        within-recording drift, unless a time is given explicitly.
    wander : WanderingLight, optional
        Each fiber's light wandering over the session's time and its day's gain (the ``real`` physics).
    colours : FiberColours, optional
        Colour-coded fibers (RGB frames): each fiber's tint, and the chromaticity a press gives it.

    Attributes
    ----------
    fiber_centres_px : ndarray, shape (N, 2), float64
        Ground truth: image point (col, row) of every fiber centre, layout order.
    dark_fibers : tuple of int
        Ground truth: layout indices of fibers that transmit nothing.
    rest_peak : ndarray, shape (N,), float64
        Ground truth: nominal rest peak gray level above background of every
        fiber (day 0; multiply by :meth:`brightness` for the session's level).
    frame_index : int
        Frames rendered so far (the clock of the within-recording drift).
    last_real_indenters : tuple of Indenter
        The indenters as really pressed (depth jittered) in the last call of
        :meth:`darkening`.
    layout, optics, skin, drift, fps, renderer
        As given / built.

    A *press* is a run of :meth:`darkening` / :meth:`frame` calls with equal
    indenters; its real depths are drawn once, at its first call (a call with
    no indenters ends a press).
    """

    def __init__(  # noqa: PLR0913
        self,
        layout: FiberLayout | None = None,
        optics: CameraOptics = DEFAULT_OPTICS,
        skin: SkinModel = DEFAULT_SKIN,
        seed: int = 0,
        sensor_seed: int = SENSOR_SEED,
        drift: SessionDrift = NO_DRIFT,
        fps: float = 60.0,
        wander: WanderingLight | None = None,
        colours: FiberColours | None = None,
    ) -> None:
        if not fps > 0:
            raise ValueError("fps must be > 0")
        self.layout = hex_layout() if layout is None else layout
        self.optics = optics
        self.skin = skin
        self.seed = seed
        self.sensor_seed = sensor_seed
        self.drift = drift
        self.fps = float(fps)
        self.wander = wander
        self.colours = colours
        self.renderer = FrameRenderer(
            self.layout,
            optics,
            sensor_seed=sensor_seed,
            noise_seed=seed,
            shift_px=drift.camera_shift_px,
        )
        self._rng = np.random.default_rng([seed, 3])
        self._depth_rng = np.random.default_rng([seed, drift.seed, 4])
        self._fiber_rates = drift.fiber_drift_rates(self.layout.n_fibers, sensor_seed)
        self._press: tuple[Indenter, ...] = ()
        self.last_real_indenters: tuple[Indenter, ...] = ()
        self.frame_index = 0

    @property
    def fiber_centres_px(self) -> np.ndarray:
        return self.renderer.fiber_centres_px

    @property
    def dark_fibers(self) -> tuple[int, ...]:
        return tuple(self.optics.dark_fibers)

    @property
    def rest_peak(self) -> np.ndarray:
        return self.renderer.rest_peak

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return self.renderer.frame_shape

    def real_indenters(self, indenters: Sequence[Indenter] = ()) -> tuple[Indenter, ...]:
        """``indenters`` with the session's per-press depth jitter applied.

        The same indenters as in the previous call are the same press and keep
        their real depths; anything else (or no indenters) starts a new press.
        """
        press = tuple(indenters)
        if press != self._press:
            self._press = press
            jitter = self.drift.depth_jitter
            if jitter and press:
                z = np.clip(self._depth_rng.standard_normal(len(press)), -2.5, 2.5)
                self.last_real_indenters = tuple(
                    replace(ind, depth_mm=ind.depth_mm * float(1.0 + jitter * zi))
                    for ind, zi in zip(press, z)
                )
            else:
                self.last_real_indenters = press
        return self.last_real_indenters

    def darkening(self, indenters: Sequence[Indenter] = ()) -> np.ndarray:
        """Fraction of light each fiber loses, shape (N,), float64.

        :func:`fiber_darkening` of :meth:`real_indenters`, times the session's
        ``pin_gain`` (clipped to [0, 1]); for the nominal day exactly
        :func:`fiber_darkening`.
        """
        return self.press_darkening(self.real_indenters(indenters))

    def press_darkening(self, real_indenters: Sequence[Indenter]) -> np.ndarray:
        """:meth:`darkening` of indenters already at their real depths (no jitter drawn): a press that
        moves or changes depth keeps the depth error it started with."""
        d = fiber_darkening(self.layout.xy_mm, tuple(real_indenters), self.skin)
        if self.drift.pin_gain != 1.0:
            d = np.clip(d * self.drift.pin_gain, 0.0, 1.0)
        return d

    def brightness(self, t_s: float) -> np.ndarray | float:
        """The session's brightness factor at ``t_s`` s: a float, or (N,) with per-fiber drift."""
        if self.drift.fiber_drift_per_s:
            return self.drift.brightness(t_s, self._fiber_rates)
        return self.drift.brightness(t_s)

    def frame(self, indenters: Sequence[Indenter] = (), t_s: float | None = None) -> np.ndarray:
        """The camera frame with ``indenters`` pressed in (none: a rest frame).

        ``t_s``: time in the recording for the within-recording drift (default
        :attr:`frame_index` / ``fps``).

        Returns
        -------
        ndarray, uint8, shape (H, W) or (H, W, 3)
        """
        return self.frame_from_darkening(self.darkening(indenters), t_s)

    def frame_from_darkening(self, darkening: np.ndarray, t_s: float | None = None) -> np.ndarray:
        """The camera frame for a given per-fiber darkening, shape (N,) in [0, 1].

        The darkening is used as given (no pin gain, no depth jitter); the
        session's brightness at ``t_s`` (default :attr:`frame_index` / ``fps``) applies.
        """
        t = self.frame_index / self.fps if t_s is None else float(t_s)
        gain = 1.0 - np.asarray(darkening, dtype=np.float64)
        b = self.brightness(t)
        if np.any(np.asarray(b) != 1.0):
            gain = gain * b
        if self.wander is not None:
            gain = gain * self.wander.factor(t)
        self.frame_index += 1
        rgb = None if self.colours is None else self.colours.rgb(np.asarray(darkening, dtype=np.float64))
        return self.renderer.render(gain, self._rng, rgb)
