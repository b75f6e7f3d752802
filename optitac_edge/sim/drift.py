"""Day-to-day drift of a simulated sensor, and other simulated sensors.

:class:`SessionDrift` is the "day" a recording is made on: the camera shifted by
a fraction of a pixel, the LEDs and the pins' response a few percent off, every
press's real depth a few percent off the commanded one, and optionally a slow
brightness drift within the recording (LED warm-up). Day 0 is nominal (no drift);
:meth:`SessionDrift.for_day` draws any other day reproducibly.

:func:`sensor_variant` draws a plausible *different* sensor (camera geometry,
lens, illumination, noise and skin response); variant 0 is the default sensor.
:func:`variant_sensor_seed` gives the variant's physical-sensor seed (fiber
transmission spread, fixed-pattern noise).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from optitac_edge.core.layout import FiberLayout, hex_layout
from optitac_edge.sim.optics import CameraOptics
from optitac_edge.sim.render import SENSOR_SEED, fiber_rest_peak
from optitac_edge.sim.skin import SkinModel


@dataclass(frozen=True)
class SessionDrift:
    """How one recording session (a "day") differs from the nominal sensor.

    The default instance is the nominal day: no drift at all, and frames are
    bit-identical to a sensor built without a drift.

    Attributes
    ----------
    camera_shift_px : tuple of 2 float
        (dx, dy) = (columns, rows) shift of the whole image of the fiber array,
        px; exact (the face centres move before the per-pixel maps are built).
        The camera's own fixed-pattern noise does not move. Default (0, 0).
    led_gain : float
        Global brightness factor of the fiber light (default 1).
    pin_gain : float
        Skin response factor: every fiber's darkening is multiplied by it
        (clipped to [0, 1]) (default 1).
    depth_jitter : float
        Relative sigma of each press's real depth vs the commanded one:
        ``real = commanded * (1 + depth_jitter * z)``, z ~ N(0, 1) clipped at
        +-2.5, one draw per press (default 0). ``truth.csv`` keeps the
        commanded depth.
    led_drift_per_s : float
        Slow within-recording brightness drift (LED warm-up), relative per
        second: brightness = ``led_gain * (1 + led_drift_per_s * t)`` (default 0).
    fiber_drift_per_s : float
        Per-fiber slow drift: every fiber's brightness is multiplied by
        ``1 + r_i * t`` with r_i ~ N(0, fiber_drift_per_s) per second (default 0).
    seed : int
        Seed of this day's own randomness (per-press depth factors together with
        the recording's noise seed; per-fiber drift rates together with the
        sensor seed) (default 0).
    """

    camera_shift_px: tuple[float, float] = (0.0, 0.0)
    led_gain: float = 1.0
    pin_gain: float = 1.0
    depth_jitter: float = 0.0
    led_drift_per_s: float = 0.0
    fiber_drift_per_s: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if len(self.camera_shift_px) != 2:
            raise ValueError("camera_shift_px must be (dx, dy)")
        if not self.led_gain > 0 or not self.pin_gain >= 0:
            raise ValueError("led_gain must be > 0 and pin_gain >= 0")
        if self.depth_jitter < 0 or self.fiber_drift_per_s < 0:
            raise ValueError("depth_jitter and fiber_drift_per_s must be >= 0")
        object.__setattr__(self, "camera_shift_px", tuple(float(v) for v in self.camera_shift_px))

    @property
    def is_nominal(self) -> bool:
        """True if this drift changes nothing (the seed aside)."""
        return replace(self, seed=0) == SessionDrift()

    def to_dict(self) -> dict[str, object]:
        """JSON-able dict of all fields (tuples become lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def for_day(
        cls, day: int, sensor_seed: int = SENSOR_SEED, led_drift: bool = True, scale: float = 1.0
    ) -> SessionDrift:
        """A reproducible random day of the sensor ``sensor_seed``; day 0 is nominal.

        Every other day has every kind of drift at a clearly non-zero strength
        (magnitudes drawn from the upper half of the range, random signs):

        - camera shift: each of dx, dy in +-[0.15, 0.5] px;
        - ``led_gain``, ``pin_gain``: 1 +-[0.02, 0.05];
        - ``depth_jitter``: [0.03, 0.05];
        - ``led_drift_per_s``: +-[0.0005, 0.0015] /s (0.5-1.5 % over a 10 s
          recording), 0 when ``led_drift`` is False;
        - ``fiber_drift_per_s``: 0.0003 /s when ``led_drift`` (0.3 % sigma over 10 s).

        ``scale`` multiplies the LED and pin gain changes (a sensor that drifts more between days, see
        :mod:`optitac_edge.sim.physics`); 1 (default) draws exactly the days above.
        """
        if day < 0:
            raise ValueError("day must be >= 0")
        if not scale > 0:
            raise ValueError("scale must be > 0")
        if day == 0:
            return cls()
        rng = np.random.default_rng([sensor_seed, day, 77])

        def signed(lo: float, hi: float) -> float:
            return float(rng.choice([-1.0, 1.0]) * rng.uniform(lo, hi))

        shift = (signed(0.15, 0.5), signed(0.15, 0.5))
        led_gain = 1.0 + scale * signed(0.02, 0.05)
        pin_gain = 1.0 + scale * signed(0.02, 0.05)
        jitter = float(rng.uniform(0.03, 0.05))
        drift = signed(0.0005, 0.0015)
        return cls(
            camera_shift_px=(round(shift[0], 4), round(shift[1], 4)),
            led_gain=round(led_gain, 5),
            pin_gain=round(pin_gain, 5),
            depth_jitter=round(jitter, 5),
            led_drift_per_s=round(drift, 6) if led_drift else 0.0,
            fiber_drift_per_s=0.0003 if led_drift else 0.0,
            seed=int(day),
        )

    def fiber_drift_rates(self, n_fibers: int, sensor_seed: int = SENSOR_SEED) -> np.ndarray:
        """Per-fiber relative drift rates r_i (1/s), shape (N,); zeros if no fiber drift."""
        if self.fiber_drift_per_s == 0:
            return np.zeros(n_fibers)
        rng = np.random.default_rng([sensor_seed, self.seed, 5])
        return self.fiber_drift_per_s * rng.standard_normal(n_fibers)

    def brightness(self, t_s: float, rates: np.ndarray | None = None) -> np.ndarray | float:
        """Brightness factor at time ``t_s`` (s): global, or per fiber given ``rates``."""
        led = self.led_gain * (1.0 + self.led_drift_per_s * t_s)
        return led if rates is None else led * (1.0 + rates * t_s)


#: The nominal day (frozen, safe to share).
NO_DRIFT = SessionDrift()

#: Largest rest level (background + brightest fiber peak) a variant may have at
#: nominal brightness, gray levels: leaves room for +5 % LED gain, a few % of
#: warm-up and 4 sigma of noise below 255.
MAX_REST_LEVEL = 222.0

#: Margin (px) between the outermost lit pixel of a variant and the image border.
EDGE_MARGIN_PX = 4.0


def variant_sensor_seed(variant: int) -> int:
    """Physical-sensor seed of ``variant`` (:data:`SENSOR_SEED` for variant 0)."""
    return SENSOR_SEED if variant == 0 else SENSOR_SEED + 7919 * int(variant)


def _lit_extent(optics: CameraOptics, layout: FiberLayout) -> tuple[np.ndarray, np.ndarray]:
    """Min and max image point (col, row) of any lit pixel (face radius + 4 sigma blur)."""
    proj = optics.projection(layout.radius_mm)
    centres = proj.to_image(layout.xy_mm)
    reach = optics.fiber_diameter_mm / 2 * proj.scale + 4 * max(optics.blur_sigma_px, 0.3) + 1
    return centres.min(axis=0) - reach, centres.max(axis=0) + reach


def sensor_variant(
    variant: int,
    width: int = 640,
    height: int = 480,
    layout: FiberLayout | None = None,
    base: SkinModel | None = None,
) -> tuple[dict[str, Any], SkinModel]:
    """A reproducible, plausible different sensor; variant 0 is the default one.

    Parameters
    ----------
    variant : int
        >= 0. 0: ``({}, SkinModel())``.
    width, height : int
        Frame size the variant is drawn for (the centre offset is fitted to it).
    layout : FiberLayout or None
        Fiber layout (default hex_layout()).
    base : SkinModel or None
        The skin the variant's is drawn around (default ``SkinModel()``; a simulated physics',
        :mod:`optitac_edge.sim.physics`): variant 0 is ``base`` itself.

    Returns
    -------
    overrides : dict
        :class:`CameraOptics` fields to replace (``dataclasses.replace(optics,
        **overrides)``): ``fill_fraction`` 0.6-0.9, ``rotation_deg`` 0-360,
        ``mirror``, ``centre_offset_px`` (anywhere that keeps every lit pixel
        :data:`EDGE_MARGIN_PX` inside the frame), ``k1`` +-0.03, ``k2`` 0-0.008,
        ``p1``, ``p2`` +-0.002, ``blur_sigma_px`` 0.7-1.5, ``face_falloff``
        0.05-0.25, ``background_gray`` 6-16, ``noise_sigma`` 1-3,
        ``row_noise_sigma`` 0.2-1.0, ``led_peak_gray`` 120-210 (lowered if the
        brightest fiber would exceed :data:`MAX_REST_LEVEL`),
        ``transmission_sigma`` 0.05-0.12, ``vignetting`` 0-0.25. Not touched:
        width, height, rgb, rgb_gains, dark_fibers, fiber_diameter_mm.
    skin : SkinModel
        max_darkening, compression_gain, tilt_gain, spread_mm,
        spread_per_depth, clamp_margin_mm, rim_width_mm each x U(0.75, 1.25)
        (max_darkening x U(0.75, 1.1), i.e. 0.64-0.94); modulus_mpa x U(0.75, 1.25) (from
        its own random stream); indenter geometry (ellipse ratio, edge length), grid step,
        stiffening_mm and rim_stiffening unchanged.

    The variant's transmission pattern comes from :func:`variant_sensor_seed`.
    """
    if variant < 0:
        raise ValueError("variant must be >= 0")
    base = SkinModel() if base is None else base
    if variant == 0:
        return {}, base
    layout = hex_layout() if layout is None else layout
    rng = np.random.default_rng([int(variant), 4242])
    u = rng.uniform
    ov: dict[str, Any] = {
        "fill_fraction": float(u(0.6, 0.9)),
        "rotation_deg": float(u(0.0, 360.0)),
        "mirror": bool(rng.integers(0, 2)),
        "k1": float(u(-0.03, 0.03)),
        "k2": float(u(0.0, 0.008)),
        "p1": float(u(-0.002, 0.002)),
        "p2": float(u(-0.002, 0.002)),
        "blur_sigma_px": float(u(0.7, 1.5)),
        "face_falloff": float(u(0.05, 0.25)),
        "background_gray": float(u(6.0, 16.0)),
        "noise_sigma": float(u(1.0, 3.0)),
        "row_noise_sigma": float(u(0.2, 1.0)),
        "led_peak_gray": float(u(120.0, 210.0)),
        "transmission_sigma": float(u(0.05, 0.12)),
        "vignetting": float(u(0.0, 0.25)),
    }
    offset_frac = u(-1.0, 1.0, 2)
    skin_f = [float(f) for f in u(0.75, 1.25, 7)]
    skin_f[0] = float(u(0.75, 1.1))  # max_darkening 0.64-0.94: a fiber never goes fully dark
    skin = _variant_skin(base, skin_f, variant)
    _fit_in_frame(ov, layout, variant, (width, height), offset_frac)
    ov = {k: round(v, 6) if isinstance(v, float) else v for k, v in ov.items()}
    return ov, skin


def _variant_skin(base: SkinModel, f: list[float], variant: int) -> SkinModel:
    """``base`` with its fields scaled by the variant's factors ``f`` (and its modulus by a stream of its own)."""
    return replace(
        base,
        max_darkening=base.max_darkening * f[0],
        compression_gain=base.compression_gain * f[1],
        tilt_gain=base.tilt_gain * f[2],
        spread_mm=base.spread_mm * f[3],
        spread_per_depth=base.spread_per_depth * f[4],
        clamp_margin_mm=base.clamp_margin_mm * f[5],
        rim_width_mm=base.rim_width_mm * f[6],
        # a stream of its own: the draws above (and every variant's skin) stay as they were
        modulus_mpa=base.modulus_mpa * float(np.random.default_rng([variant, 77]).uniform(0.75, 1.25)),
    )


def _fit_in_frame(ov: dict[str, Any], layout: FiberLayout, variant: int, frame: tuple[int, int],
                  offset_frac: np.ndarray) -> None:
    """Make the variant's optics ``ov`` (in place) fit a ``frame`` (width, height): the brightest rest fiber
    capped (no saturation), the fill shrunk until the array fits, then the array placed anywhere it stays
    inside (``offset_frac`` of the room, each in -1..1)."""
    width, height = frame
    optics = replace(CameraOptics(width=width, height=height), **ov)
    peak = fiber_rest_peak(layout, optics, variant_sensor_seed(variant)).max()
    room = MAX_REST_LEVEL - float(ov["background_gray"])
    if peak > room:
        ov["led_peak_gray"] = float(float(ov["led_peak_gray"]) * 0.999 * room / peak)
    size = np.array([width, height], dtype=float)
    for _ in range(20):
        optics = replace(
            CameraOptics(width=width, height=height), **ov, centre_offset_px=(0.0, 0.0)
        )
        lo, hi = _lit_extent(optics, layout)
        slack = np.minimum(lo, size - 1 - hi) - EDGE_MARGIN_PX - 0.6  # 0.6: day's camera shift
        if np.all(slack >= 0):
            break
        ov["fill_fraction"] = float(ov["fill_fraction"]) * 0.97
    else:  # pragma: no cover - only for absurdly small frames
        raise ValueError(f"the array does not fit a {width} x {height} frame")
    ov["centre_offset_px"] = (
        round(float(offset_frac[0] * slack[0]), 3),
        round(float(offset_frac[1] * slack[1]), 3),
    )


def variant_optics(variant: int, optics: CameraOptics | None = None) -> CameraOptics:
    """``optics`` (default CameraOptics()) with :func:`sensor_variant`'s overrides for its size."""
    optics = CameraOptics() if optics is None else optics
    overrides, _ = sensor_variant(variant, optics.width, optics.height)
    return replace(optics, **overrides)
