"""The simulated camera: where the fiber array appears in the image and how bright.

Geometry, layout (mm) -> image (px), the project's orientation contract:

1. mirror: ``x -> -x`` when ``mirror`` is set;
2. rotate counter-clockwise by ``rotation_deg`` (layout frame, +y up);
3. scale: ``du = s * x``, ``dv = -s * y`` (image rows grow downwards);
4. Brown lens distortion (radial ``k1``, ``k2``, tangential ``p1``, ``p2``) in
   coordinates normalised by ``r_ref`` = the outermost fiber's radius in px;
5. place: ``col = cx + du'``, ``row = cy + dv'``.

With rotation 0 and no mirror the layout's +x points to increasing column and
+y to decreasing row. This distortion model is the simulator's own and on
purpose not the pipeline's one-parameter model (``optitac_edge.core.image_transform``).
Pixel ``[row, col]`` has its centre at image point ``(col, row)``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class CameraOptics:
    """Camera, lens, fiber end faces and illumination of a simulated sensor.

    Attributes
    ----------
    width, height : int
        Frame size, px (default 640 x 480).
    rgb : bool
        Frames are (H, W, 3) RGB if True, else (H, W) gray (default False).
    rotation_deg : float
        The array appears rotated counter-clockwise by this angle (default 0).
    mirror : bool
        Negate layout x before rotating (default False).
    scale_px_per_mm : float or None
        Image scale; None (default): the array's outer diameter (outermost fiber
        centres plus one face diameter) fills ``fill_fraction`` of min(width, height).
    fill_fraction : float
        See ``scale_px_per_mm`` (default 0.8).
    centre_offset_px : tuple of 2 float or None
        Offset (col, row) of the array centre from the image centre, px; None
        (default): (+3 % of width, -2.5 % of height).
    k1, k2 : float
        Brown radial distortion, ``r -> r (1 + k1 r^2 + k2 r^4)`` with r normalised
        by the outermost fiber radius (defaults 0.010, 0.004: +1.4 % at the rim).
    p1, p2 : float
        Brown tangential distortion (defaults 0.001, -0.001).
    fiber_diameter_mm : float
        Diameter of a fiber end face (default 1.0).
    blur_sigma_px : float
        Gaussian defocus blur of the face edges, px (default 1.0).
    face_falloff : float
        A face is ``face_falloff`` dimmer at its edge than at its centre (default 0.15).
    background_gray : float
        Dark background level, gray levels (default 10).
    noise_sigma : float
        Temporal Gaussian noise, gray levels (default 2).
    row_noise_sigma : float
        Row-wise fixed-pattern offset, gray levels (default 0.5; 0 disables).
    led_peak_gray : float
        Peak gray level of a rest fiber of nominal transmission at mid-radius
        (default 170; with the defaults no pixel saturates).
    transmission_sigma : float
        Per-fiber multiplicative transmission spread ~ N(1, sigma), clipped at
        +-2.5 sigma (default 0.08); drawn from the sensor seed.
    vignetting : float
        LED-ring illumination: fibers are ``1 + vignetting * (2 (r/R)^2 - 1)`` bright,
        i.e. -15 % at the centre, +15 % at the rim by default.
    rgb_gains : tuple of 3 float
        Per-channel gains of the fiber light when ``rgb`` (default (1.0, 0.96, 0.88)).
    dark_fibers : tuple of int
        Layout indices (0..N-1) of fibers that transmit nothing (default ()).
    stray_light : tuple of (col, row, radius_px, gray)
        Dim blobs of stray light on the background (a reflection, a lit corner): centre, radius and gray levels
        above the background (default none).
    """

    width: int = 640
    height: int = 480
    rgb: bool = False
    rotation_deg: float = 0.0
    mirror: bool = False
    scale_px_per_mm: float | None = None
    fill_fraction: float = 0.8
    centre_offset_px: tuple[float, float] | None = None
    k1: float = 0.010
    k2: float = 0.004
    p1: float = 0.001
    p2: float = -0.001
    fiber_diameter_mm: float = 1.0
    blur_sigma_px: float = 1.0
    face_falloff: float = 0.15
    background_gray: float = 10.0
    noise_sigma: float = 2.0
    row_noise_sigma: float = 0.5
    led_peak_gray: float = 170.0
    transmission_sigma: float = 0.08
    vignetting: float = 0.15
    rgb_gains: tuple[float, float, float] = (1.0, 0.96, 0.88)
    dark_fibers: tuple[int, ...] = ()
    stray_light: tuple[tuple[float, float, float, float], ...] = ()

    def __post_init__(self) -> None:
        if self.width < 16 or self.height < 16:
            raise ValueError("frame must be at least 16 x 16 px")
        if self.fiber_diameter_mm <= 0 or self.blur_sigma_px < 0 or self.noise_sigma < 0:
            raise ValueError("fiber_diameter_mm must be > 0, blur and noise >= 0")

    def to_dict(self) -> dict[str, object]:
        """JSON-able dict of all fields (tuples become lists)."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    def projection(self, layout_radius_mm: float) -> Projection:
        """Resolve the defaults for a layout whose outermost fiber is ``layout_radius_mm`` out."""
        outer = 2.0 * (layout_radius_mm + self.fiber_diameter_mm / 2.0)
        scale = self.scale_px_per_mm or self.fill_fraction * min(self.width, self.height) / outer
        off = self.centre_offset_px
        if off is None:
            off = (0.03 * self.width, -0.025 * self.height)
        return Projection(
            optics=self,
            scale=float(scale),
            cx=(self.width - 1) / 2.0 + off[0],
            cy=(self.height - 1) / 2.0 + off[1],
            r_ref=float(scale * layout_radius_mm),
        )


#: The default camera (frozen, safe to share).
DEFAULT_OPTICS = CameraOptics()


@dataclass(frozen=True)
class Projection:
    """The resolved layout <-> image mapping of :class:`CameraOptics` for one layout.

    Attributes
    ----------
    scale : float
        px per mm. ``cx``, ``cy``: image point (col, row) of the layout origin.
    r_ref : float
        Distortion normalisation radius, px (outermost fiber radius).
    """

    optics: CameraOptics
    scale: float
    cx: float
    cy: float
    r_ref: float

    def _rot(self) -> tuple[float, float]:
        t = math.radians(self.optics.rotation_deg)
        return math.cos(t), math.sin(t)

    def _tangential(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p1, p2 = self.optics.p1, self.optics.p2
        r2 = x * x + y * y
        return 2 * p1 * x * y + p2 * (r2 + 2 * x * x), p1 * (r2 + 2 * y * y) + 2 * p2 * x * y

    def _radial(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        r2 = x * x + y * y
        return 1.0 + self.optics.k1 * r2 + self.optics.k2 * r2 * r2

    def to_image(self, xy_mm: np.ndarray) -> np.ndarray:
        """Layout points (N, 2) mm -> image points (N, 2) (col, row) px, float64."""
        xy = np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2)
        x = -xy[:, 0] if self.optics.mirror else xy[:, 0]
        c, s = self._rot()
        xr, yr = c * x - s * xy[:, 1], s * x + c * xy[:, 1]
        xn, yn = self.scale * xr / self.r_ref, -self.scale * yr / self.r_ref
        rad = self._radial(xn, yn)
        tx, ty = self._tangential(xn, yn)
        xd, yd = xn * rad + tx, yn * rad + ty
        return np.stack([self.cx + self.r_ref * xd, self.cy + self.r_ref * yd], axis=1)

    def to_layout(self, uv_px: np.ndarray, iterations: int = 8) -> np.ndarray:
        """Image points (N, 2) (col, row) px -> layout points (N, 2) mm (fixed-point undistortion)."""
        uv = np.asarray(uv_px, dtype=np.float64).reshape(-1, 2)
        xd, yd = (uv[:, 0] - self.cx) / self.r_ref, (uv[:, 1] - self.cy) / self.r_ref
        xn, yn = xd.copy(), yd.copy()
        for _ in range(iterations):
            tx, ty = self._tangential(xn, yn)
            rad = self._radial(xn, yn)
            xn, yn = (xd - tx) / rad, (yd - ty) / rad
        xr, yr = xn * self.r_ref / self.scale, -yn * self.r_ref / self.scale
        c, s = self._rot()
        x, y = c * xr + s * yr, -s * xr + c * yr
        return np.stack([-x if self.optics.mirror else x, y], axis=1)
