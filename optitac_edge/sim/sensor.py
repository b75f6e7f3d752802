"""A simulated OptiTac sensor: indenters in, camera frames out, with ground truth."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..layout import FiberLayout, hex_layout
from .optics import DEFAULT_OPTICS, CameraOptics
from .render import SENSOR_SEED, FrameRenderer
from .skin import DEFAULT_SKIN, Indenter, SkinModel, fiber_darkening


class SimulatedSensor:
    """Skin model plus camera: renders the frame a real sensor would deliver.

    Parameters
    ----------
    layout : FiberLayout or None
        Fiber layout; None (default): :func:`optitac_edge.layout.hex_layout` (217 fibers).
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

    Attributes
    ----------
    fiber_centres_px : ndarray, shape (N, 2), float64
        Ground truth: image point (col, row) of every fiber centre, layout order.
    dark_fibers : tuple of int
        Ground truth: layout indices of fibers that transmit nothing.
    rest_peak : ndarray, shape (N,), float64
        Ground truth: rest peak gray level above background of every fiber.
    layout, optics, skin, renderer
        As given / built.
    """

    def __init__(
        self,
        layout: FiberLayout | None = None,
        optics: CameraOptics = DEFAULT_OPTICS,
        skin: SkinModel = DEFAULT_SKIN,
        seed: int = 0,
        sensor_seed: int = SENSOR_SEED,
    ) -> None:
        self.layout = hex_layout() if layout is None else layout
        self.optics = optics
        self.skin = skin
        self.seed = seed
        self.sensor_seed = sensor_seed
        self.renderer = FrameRenderer(self.layout, optics, sensor_seed=sensor_seed, noise_seed=seed)
        self._rng = np.random.default_rng([seed, 3])

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

    def darkening(self, indenters: Sequence[Indenter] = ()) -> np.ndarray:
        """Fraction of light each fiber loses, shape (N,), float64 (see :func:`fiber_darkening`)."""
        return fiber_darkening(self.layout.xy_mm, indenters, self.skin)

    def frame(self, indenters: Sequence[Indenter] = ()) -> np.ndarray:
        """The camera frame with ``indenters`` pressed in (none: a rest frame).

        Returns
        -------
        ndarray, uint8, shape (H, W) or (H, W, 3)
        """
        return self.frame_from_darkening(self.darkening(indenters))

    def frame_from_darkening(self, darkening: np.ndarray) -> np.ndarray:
        """The camera frame for a given per-fiber darkening, shape (N,) in [0, 1]."""
        return self.renderer.render(1.0 - np.asarray(darkening, dtype=np.float64), self._rng)
