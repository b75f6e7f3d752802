"""The skin's response to indenters: how much light each fiber loses.

Model (per indenter, on a mm grid covering the clamped skin):

1. footprint ``F``: 1 inside the indenter outline, 0 outside (signed distance,
   anti-aliased over one grid step);
2. deflection ``w = depth * clamp(r) * (F * G_L)``: the footprint smoothed by a
   Gaussian of spread ``L = spread_mm + spread_per_depth * depth`` (the skin
   drapes around the indenter), forced to 0 at the clamped rim by
   ``clamp(r) = tanh(max(Rc - r, 0) / rim_width_mm)`` with ``Rc`` the outermost
   fiber radius plus ``clamp_margin_mm``;
3. darkening ``d = max_darkening * R(s)`` with ``s = compression_gain * w + tilt_gain * |grad w_t|``:
   pins pressed in (``w``) and pins tilted by the skin's slope both turn their
   white tips away from the fiber. ``R`` is the pins' response (``response``):
   ``saturating`` ``1 - exp(-s)`` (default), ``linear`` ``min(s, 1)``, or
   ``threshold`` ``1 - exp(-max(s - response_threshold, 0))`` (pins that stick
   until pushed far enough). ``w_t`` is ``w`` smoothed by a further Gaussian of
   ``tilt_spread_mm`` (0, default: ``w`` itself): a skin whose pins tilt further
   out than it deflects.

A domed indenter (``dome`` > 0) touches first at its centre: inside its
outline the skin is pressed to ``max(depth - q^2 / (2 R), 0)`` with ``q`` the
distance from the indenter's centre and ``R = dome * bounding radius`` (a
5 mm circle with ``dome = 1`` is a 5 mm ball), so its footprint grows with
depth; ``dome = 0`` (default) is a flat punch.

Several indenters combine as ``1 - prod(1 - d_i)``.

Normal force (the simulator's load cell, :func:`contact_force_n`): a flat punch
on an elastic layer, ``F = 2 E* a δ (1 + δ / δs) (1 + k_rim (r / Rc)²)`` with
``a = sqrt(footprint area / π)`` the equivalent punch radius (a domed indenter:
``min(a, sqrt(R δ))``, Hertz's contact radius), ``δ`` the depth,
``E*`` the skin's effective modulus, ``δs`` the depth at which the stretched
membrane doubles the stiffness, and the clamped rim stiffening the skin
towards ``Rc`` (the clamp radius). It is documented in docs/simulator.md;
depth and force calibration (``calibrate depth``) are evaluated against it.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
from scipy.ndimage import gaussian_filter, map_coordinates

from optitac_edge.io.recording import SHAPES


@dataclass(frozen=True)
class Indenter:
    """One rigid flat indenter pressed into the skin.

    Attributes
    ----------
    shape : str
        One of ``edge``, ``circle``, ``square``, ``ellipse``, ``triangle``.
    x_mm, y_mm : float
        Centre (centroid) in the layout frame, mm.
    angle_deg : float
        Counter-clockwise rotation, degrees. At 0 an ellipse's major axis and an
        edge's long axis lie along +x, a square's sides are axis-aligned and a
        triangle has a vertex pointing to +y.
    size_mm : float
        Circle: diameter; square and (equilateral) triangle: side; ellipse: major
        axis; edge: width of the bar.
    depth_mm : float
        Indentation depth, mm (>= 0).
    """

    shape: str
    x_mm: float
    y_mm: float
    angle_deg: float = 0.0
    size_mm: float = 5.0
    depth_mm: float = 3.0

    def __post_init__(self) -> None:
        if self.shape not in SHAPES:
            raise ValueError(f"unknown indenter shape {self.shape!r}; expected one of {SHAPES}")
        if not self.size_mm > 0 or not self.depth_mm >= 0:
            raise ValueError("size_mm must be > 0 and depth_mm >= 0")


@dataclass(frozen=True)
class SkinModel:
    """Response parameters of the skin (see the module docstring for the model).

    Attributes
    ----------
    max_darkening : float
        Largest fraction of light a fiber can lose (default 0.85).
    compression_gain : float
        Darkening rate per mm of deflection, 1/mm (default 0.45).
    tilt_gain : float
        Darkening rate per unit skin slope (default 0.4).
    spread_mm, spread_per_depth : float
        Spread of the deflection ``L = spread_mm + spread_per_depth * depth``
        (defaults 0.9 mm and 0.2 mm/mm: 1.5 mm at 3 mm depth).
    clamp_margin_mm : float
        Skin clamped at the outermost fiber radius plus this (default 1.0).
    rim_width_mm : float
        Length over which the clamp suppresses deflection (default 6.0).
    ellipse_ratio : float
        Minor / major axis of an ellipse indenter (default 0.6).
    edge_length_mm : float
        Length of an edge indenter's bar (default 12).
    grid_step_mm : float
        Resolution of the deflection grid (default 0.2).
    modulus_mpa : float
        Effective modulus ``E*`` of the skin for the normal force, N/mm² (default 0.12).
    stiffening_mm : float
        Depth ``δs`` at which the membrane doubles the skin's stiffness, mm (default 4).
    rim_stiffening : float
        ``k_rim``: how much stiffer the skin is at the clamp radius than at the centre (default 1: twice).
    response : str
        The pins' response ``R``: ``saturating`` (default), ``linear`` or ``threshold``.
    response_threshold : float
        ``threshold`` response: the ``s`` below which a pin does not turn (default 0.15).
    tilt_spread_mm : float
        Further spread of the slope that tilts the pins, mm (default 0).
    dome : float
        The indenter's face: 0 flat (default); > 0 a sphere of ``dome`` times its bounding radius.
    """

    max_darkening: float = 0.85
    compression_gain: float = 0.45
    tilt_gain: float = 0.4
    spread_mm: float = 0.9
    spread_per_depth: float = 0.2
    clamp_margin_mm: float = 1.0
    rim_width_mm: float = 6.0
    ellipse_ratio: float = 0.6
    edge_length_mm: float = 12.0
    grid_step_mm: float = 0.2
    modulus_mpa: float = 0.12
    stiffening_mm: float = 4.0
    rim_stiffening: float = 1.0
    response: str = "saturating"
    response_threshold: float = 0.15
    tilt_spread_mm: float = 0.0
    dome: float = 0.0

    def __post_init__(self) -> None:
        if self.response not in RESPONSES:
            raise ValueError(f"unknown skin response {self.response!r}; expected one of {RESPONSES}")
        if not (self.tilt_spread_mm >= 0 and self.dome >= 0 and self.response_threshold >= 0):
            raise ValueError("tilt_spread_mm, dome and response_threshold must be >= 0")

    def to_dict(self) -> dict[str, float | str]:
        """JSON-able dict of all fields."""
        return asdict(self)


#: The pins' responses :class:`SkinModel` knows.
RESPONSES = ("saturating", "linear", "threshold")

#: The default skin (frozen, safe to share).
DEFAULT_SKIN = SkinModel()


def _box(px: np.ndarray, py: np.ndarray, hx: float, hy: float) -> np.ndarray:
    qx, qy = np.abs(px) - hx, np.abs(py) - hy
    outside = np.hypot(np.maximum(qx, 0), np.maximum(qy, 0))
    return outside + np.minimum(np.maximum(qx, qy), 0)


def _ellipse(px: np.ndarray, py: np.ndarray, a: float, b: float) -> np.ndarray:
    k0 = np.hypot(px / a, py / b)
    k1 = np.hypot(px / (a * a), py / (b * b))
    outside = k0 * (k0 - 1.0) / np.maximum(k1, 1e-12)
    return np.where(k0 >= 1.0, outside, (k0 - 1.0) * min(a, b))  # inside: a lower bound


def _triangle(px: np.ndarray, py: np.ndarray, side: float) -> np.ndarray:
    # Equilateral triangle centred on its centroid, a vertex towards +y (I. Quilez).
    r, k = side / 2.0, math.sqrt(3.0)
    x, y = np.abs(px) - r, py + r / k
    fold = x + k * y > 0
    x, y = np.where(fold, (x - k * y) / 2, x), np.where(fold, (-k * x - y) / 2, y)
    x = x - np.clip(x, -2 * r, 0)
    return -np.hypot(x, y) * np.sign(y)


def signed_distance(
    indenter: Indenter, x_mm: np.ndarray, y_mm: np.ndarray, skin: SkinModel
) -> np.ndarray:
    """Signed distance (mm, negative inside) from points to the indenter outline.

    Exact for circle, square, edge and triangle; a close approximation for the ellipse.
    ``x_mm`` and ``y_mm`` are float arrays of any (equal) shape; the result has that shape.
    """
    t = math.radians(indenter.angle_deg)
    dx, dy = x_mm - indenter.x_mm, y_mm - indenter.y_mm
    px, py = math.cos(t) * dx + math.sin(t) * dy, -math.sin(t) * dx + math.cos(t) * dy
    s = indenter.size_mm
    if indenter.shape == "circle":
        return np.hypot(px, py) - s / 2
    if indenter.shape == "square":
        return _box(px, py, s / 2, s / 2)
    if indenter.shape == "edge":
        return _box(px, py, skin.edge_length_mm / 2, s / 2)
    if indenter.shape == "ellipse":
        return _ellipse(px, py, s / 2, skin.ellipse_ratio * s / 2)
    return _triangle(px, py, s)


def bounding_radius(indenter: Indenter, skin: SkinModel) -> float:
    """Largest distance (mm) of the indenter outline from its centre."""
    s = indenter.size_mm
    return {
        "circle": s / 2,
        "square": s / math.sqrt(2),
        "ellipse": s / 2,
        "triangle": s / math.sqrt(3),
        "edge": math.hypot(skin.edge_length_mm / 2, s / 2),
    }[indenter.shape]


def fiber_darkening(
    layout_xy_mm: np.ndarray, indenters: Sequence[Indenter], skin: SkinModel = DEFAULT_SKIN
) -> np.ndarray:
    """Fraction of light each fiber loses under ``indenters``.

    Each indenter's skin field is computed on the window of the skin's grid it can reach (its outline, the
    two blurs' reach and the gradient's): outside it every value is exactly 0, so the result equals the
    whole grid's (:func:`fiber_darkening_whole_grid`, the tests' oracle) bit for bit.

    Parameters
    ----------
    layout_xy_mm : ndarray, shape (N, 2), float
        Fiber positions in the layout frame, mm.
    indenters : sequence of Indenter
        Simultaneous contacts (may be empty).
    skin : SkinModel
        Response parameters.

    Returns
    -------
    ndarray, shape (N,), float64
        Darkening in [0, ``skin.max_darkening``]; 0 = untouched.
    """
    return _combined(layout_xy_mm, indenters, skin, windowed=True)


def fiber_darkening_whole_grid(
    layout_xy_mm: np.ndarray, indenters: Sequence[Indenter], skin: SkinModel = DEFAULT_SKIN
) -> np.ndarray:
    """:func:`fiber_darkening` on the whole skin grid for every indenter (slower; the tests' oracle)."""
    return _combined(layout_xy_mm, indenters, skin, windowed=False)


def _combined(layout_xy_mm: np.ndarray, indenters: Sequence[Indenter], skin: SkinModel, windowed: bool
              ) -> np.ndarray:
    """:func:`fiber_darkening`, each indenter on its window of the grid (``windowed``) or on the whole grid."""
    xy = np.asarray(layout_xy_mm, dtype=np.float64)
    active = [ind for ind in indenters if ind.depth_mm > 0]
    if not active:
        return np.zeros(len(xy))
    g = _skin_grid(xy.tobytes(), skin)
    keep = np.ones(len(xy))
    for ind in active:
        window = _window(ind, skin, g) if windowed else _WHOLE
        if window is None:
            continue  # wholly off the skin's grid: no fiber is reached
        rows, cols = window
        coords = g.coords - np.array([[rows.start], [cols.start]], dtype=np.float64)
        keep *= 1.0 - _darkening(ind, skin, g.gx[window], g.gy[window], g.clamp[window], coords)
    return np.clip(1.0 - keep, 0.0, skin.max_darkening)


#: The whole grid, as a window.
_WHOLE = (slice(0, None), slice(0, None))


def _spread_mm(ind: Indenter, skin: SkinModel) -> float:
    """The first blur's sigma under ``ind``, mm (it widens with the depth)."""
    return skin.spread_mm + skin.spread_per_depth * ind.depth_mm


def _window(ind: Indenter, skin: SkinModel, g: _SkinGrid) -> tuple[slice, slice] | None:
    """The rows and columns of the grid ``ind`` can change (None: none of them; the whole grid where its
    position is not finite, as the whole grid's computation does)."""
    h, size = skin.grid_step_mm, g.axis.size
    # the reach beyond the outline, grid steps: the blurs' kernels (scipy: int(4 sigma + 0.5) each), the
    # gradient's neighbour and the interpolation's, and one step for the outline's soft edge
    reach = _kernel_radius(_spread_mm(ind, skin) / h) + 4
    if skin.tilt_spread_mm > 0:
        reach += _kernel_radius(skin.tilt_spread_mm / h)
    row, col = float((g.axis[-1] - ind.y_mm) / h), float((ind.x_mm - g.axis[0]) / h)
    extent = bounding_radius(ind, skin) / h
    if not (math.isfinite(row) and math.isfinite(col) and math.isfinite(extent)):
        return _WHOLE
    half = math.ceil(extent) + 2 + reach
    r0, r1 = max(round(row) - half, 0), min(round(row) + half + 1, size)
    c0, c1 = max(round(col) - half, 0), min(round(col) + half + 1, size)
    return (slice(r0, r1), slice(c0, c1)) if r0 < r1 and c0 < c1 else None


def _kernel_radius(sigma: float) -> int:
    """The radius of scipy's Gaussian kernel for ``sigma`` (``gaussian_filter``'s default ``truncate=4.0``)."""
    return int(4.0 * float(sigma) + 0.5)


@dataclass(frozen=True, eq=False)
class _SkinGrid:
    """The skin's grid over a layout: its axis, points (``gx``, ``gy``, row 0 = largest y), the clamp's
    weight and the fibers' fractional grid indices (row, col), shape (2, N)."""

    axis: np.ndarray
    gx: np.ndarray
    gy: np.ndarray
    clamp: np.ndarray
    coords: np.ndarray


@functools.lru_cache(maxsize=8)
def _skin_grid(xy_bytes: bytes, skin: SkinModel) -> _SkinGrid:
    """:class:`_SkinGrid` of the fiber positions ``xy_bytes`` (float64, (N, 2)); the same every frame."""
    xy = np.frombuffer(xy_bytes, dtype=np.float64).reshape(-1, 2)
    clamp_r = clamp_radius_mm(xy, skin)
    h = skin.grid_step_mm
    half = clamp_r + h
    axis = np.arange(-half, half + h / 2, h)
    gx, gy = np.meshgrid(axis, axis[::-1])  # row 0 = largest y
    clamp = np.tanh(np.maximum(clamp_r - np.hypot(gx, gy), 0.0) / skin.rim_width_mm)
    coords = np.stack([(axis[-1] - xy[:, 1]) / h, (xy[:, 0] - axis[0]) / h])
    grid = _SkinGrid(axis, gx, gy, clamp, coords)
    for a in (axis, gx, gy, clamp, coords):
        a.flags.writeable = False
    return grid


def _darkening(ind: Indenter, skin: SkinModel, gx: np.ndarray, gy: np.ndarray, clamp: np.ndarray,
               coords: np.ndarray) -> np.ndarray:
    """One indenter's darkening of every fiber (fibers at ``coords``, fractional indices into ``gx``'s grid)."""
    h = skin.grid_step_mm
    foot = np.clip(0.5 - signed_distance(ind, gx, gy, skin) / h, 0.0, 1.0)
    if skin.dome > 0:
        q2 = (gx - ind.x_mm) ** 2 + (gy - ind.y_mm) ** 2
        foot = foot * np.maximum(1.0 - q2 / (2.0 * dome_radius_mm(ind, skin) * ind.depth_mm), 0.0)
    w = ind.depth_mm * clamp * gaussian_filter(foot, _spread_mm(ind, skin) / h, mode="constant")
    tilted = gaussian_filter(w, skin.tilt_spread_mm / h, mode="constant") if skin.tilt_spread_mm > 0 else w
    gr, gc = np.gradient(tilted, h)
    slope = np.hypot(gr, gc)
    wf = map_coordinates(w, coords, order=1, mode="constant")
    sf = map_coordinates(slope, coords, order=1, mode="constant")
    return skin.max_darkening * pin_response(skin.compression_gain * wf + skin.tilt_gain * sf, skin)


def pin_response(s: np.ndarray, skin: SkinModel = DEFAULT_SKIN) -> np.ndarray:
    """The pins' response ``R(s)`` in [0, 1] (see the module docstring), same shape as ``s``."""
    if skin.response == "linear":
        return np.clip(s, 0.0, 1.0)
    if skin.response == "threshold":
        return 1.0 - np.exp(-np.maximum(s - skin.response_threshold, 0.0))
    return 1.0 - np.exp(-s)


def dome_radius_mm(indenter: Indenter, skin: SkinModel = DEFAULT_SKIN) -> float:
    """``R``: the radius of a domed indenter's face, mm (``skin.dome`` times its bounding radius)."""
    return skin.dome * bounding_radius(indenter, skin)


def clamp_radius_mm(layout_xy_mm: np.ndarray, skin: SkinModel = DEFAULT_SKIN) -> float:
    """``Rc``: where the skin is clamped, the outermost fiber's radius plus ``skin.clamp_margin_mm``."""
    return float(np.linalg.norm(np.asarray(layout_xy_mm, dtype=np.float64), axis=1).max()) + skin.clamp_margin_mm


def footprint_area_mm2(indenter: Indenter, skin: SkinModel = DEFAULT_SKIN) -> float:
    """Area of the indenter's flat face, mm² (an edge: its bar, ``edge_length_mm`` long)."""
    s = indenter.size_mm
    return {
        "circle": math.pi * s * s / 4,
        "square": s * s,
        "ellipse": math.pi * s * s * skin.ellipse_ratio / 4,
        "triangle": math.sqrt(3.0) * s * s / 4,
        "edge": skin.edge_length_mm * s,
    }[indenter.shape]


def contact_force_n(indenter: Indenter, clamp_r_mm: float, skin: SkinModel = DEFAULT_SKIN) -> float:
    """Normal force of one indenter at its depth, N (see the module docstring).

    Parameters
    ----------
    indenter : Indenter
    clamp_r_mm : float
        ``Rc`` (:func:`clamp_radius_mm` of the layout).
    skin : SkinModel
    """
    depth = indenter.depth_mm
    if depth <= 0:
        return 0.0
    a = math.sqrt(footprint_area_mm2(indenter, skin) / math.pi)
    if skin.dome > 0:
        a = min(a, math.sqrt(dome_radius_mm(indenter, skin) * depth))
    rho = min(math.hypot(indenter.x_mm, indenter.y_mm) / clamp_r_mm, 1.0)
    return (2.0 * skin.modulus_mpa * a * depth * (1.0 + depth / skin.stiffening_mm)
            * (1.0 + skin.rim_stiffening * rho * rho))
