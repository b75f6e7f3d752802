"""Rendering camera frames of the fiber array from per-fiber light levels.

Everything that does not change between frames is computed once: which fiber's
end face each pixel shows and with what weight (a soft-edged, slightly domed,
blurred disc seen through the lens distortion), every fiber's rest brightness
(LED, transmission, vignetting, dead fibers), the fixed-pattern background and a
bank of noise drawn once and sliced at a random offset per frame.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import replace

import cv2
import numpy as np
from scipy.spatial import cKDTree
from scipy.special import erfc

from optitac_edge.core.layout import FiberLayout
from optitac_edge.sim.optics import DEFAULT_OPTICS, CameraOptics, Projection

log = logging.getLogger(__name__)

#: Default seed of the simulated sensor's own randomness (fiber transmission,
#: fixed-pattern noise): the same physical sensor in every scenario.
SENSOR_SEED = 20240611

#: Pixels whose weight is below this are left at background.
_MIN_WEIGHT = 1e-3


def fiber_rest_peak(
    layout: FiberLayout, optics: CameraOptics, sensor_seed: int = SENSOR_SEED
) -> np.ndarray:
    """Peak gray level of every fiber at rest (no contact), shape (N,), float64.

    ``led_peak_gray`` x transmission ~ N(1, ``transmission_sigma``) clipped at
    +-2.5 sigma (drawn from ``sensor_seed``) x LED-ring vignetting; 0 for
    ``dark_fibers``. Excludes the background level and RGB gains.
    """
    rng = np.random.default_rng(sensor_seed)
    s = optics.transmission_sigma
    trans = np.clip(rng.normal(1.0, s, layout.n_fibers), 1 - 2.5 * s, 1 + 2.5 * s)
    r = np.linalg.norm(layout.xy_mm, axis=1) / max(layout.radius_mm, 1e-9)
    vign = 1.0 + optics.vignetting * (2.0 * r * r - 1.0)
    peak = optics.led_peak_gray * trans * vign
    peak[list(optics.dark_fibers)] = 0.0
    return peak


class FrameRenderer:
    """Renders frames of one simulated sensor seen by one camera.

    Parameters
    ----------
    layout : FiberLayout
        The sensor's fiber layout.
    optics : CameraOptics
        Camera, lens and illumination.
    sensor_seed : int
        Seed of the physical sensor's randomness (transmission spread,
        fixed-pattern noise); default :data:`SENSOR_SEED`.
    noise_seed : int
        Seed of the bank of temporal noise (default 0).
    shift_px : tuple of 2 float
        (dx, dy) shift of the whole image of the array, px (default (0, 0)): the
        projection's centre moves before the per-pixel maps are built, so a
        sub-pixel shift is exact, not an interpolation. The fixed-pattern noise
        (a property of the camera chip) does not move.

    Attributes
    ----------
    projection : Projection
        The resolved layout <-> image mapping.
    fiber_centres_px : ndarray, shape (N, 2), float64
        True image point (col, row) of every fiber centre, layout order.
    rest_peak : ndarray, shape (N,), float64
        Rest peak gray level of every fiber above background (0 for dead ones).
    frame_shape : tuple of int
        (H, W) or (H, W, 3).
    """

    def __init__(
        self,
        layout: FiberLayout,
        optics: CameraOptics = DEFAULT_OPTICS,
        sensor_seed: int = SENSOR_SEED,
        noise_seed: int = 0,
        shift_px: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        bad = [i for i in optics.dark_fibers if not 0 <= i < layout.n_fibers]
        if bad:
            raise ValueError(f"dark_fibers {bad} out of range for {layout.n_fibers} fibers")
        self.layout = layout
        self.optics = optics
        self.projection: Projection = optics.projection(layout.radius_mm)
        dx, dy = (float(v) for v in shift_px)
        if dx or dy:
            proj = self.projection
            self.projection = replace(proj, cx=proj.cx + dx, cy=proj.cy + dy)
        self.fiber_centres_px = self.projection.to_image(layout.xy_mm)
        self.rest_peak = fiber_rest_peak(layout, optics, sensor_seed)
        self._peak32 = self.rest_peak.astype(np.float32)
        h, w = optics.height, optics.width
        channels = 3 if optics.rgb else 1
        self.frame_shape: tuple[int, ...] = (h, w, 3) if optics.rgb else (h, w)
        self._pix, self._fid, self._weight = _face_pixels(
            layout.xy_mm.astype(np.float64).tobytes(), optics.blur_sigma_px, optics.fiber_diameter_mm,
            optics.face_falloff, optics.width, optics.height, self.projection)
        sensor_rng = np.random.default_rng([sensor_seed, 1])
        rows = optics.background_gray + optics.row_noise_sigma * sensor_rng.standard_normal(h)
        base = np.repeat(rows.astype(np.float32), w * channels).reshape(h * w, channels)
        if optics.stray_light:
            base += _stray_light(optics)[:, None]
        self._buf = base.copy()  # (H*W, C), fiber pixels rewritten every frame
        self._base_pix = base[self._pix]
        self._tint = np.asarray(optics.rgb_gains if optics.rgb else (1.0,), dtype=np.float32)
        # the face pixels are ordered by fiber: fiber k's are _pix[_starts[k]:_starts[k + 1]]
        self._starts = np.searchsorted(self._fid, np.arange(layout.n_fibers + 1)).astype(np.intp)
        self._last_gain: np.ndarray | None = None  # the fibers' light in _buf (None: unknown)
        n = h * w * channels
        noise_rng = np.random.default_rng([noise_seed, 2])
        bank_size = n + max(n // 2, 65536)
        self._noise = noise_rng.standard_normal(bank_size, dtype=np.float32)
        self._noise *= np.float32(optics.noise_sigma)
        log.debug(
            "renderer %s: scale %.2f px/mm, %d face pixels",
            self.frame_shape,
            self.projection.scale,
            self._pix.size,
        )

    def render(self, fiber_gain: np.ndarray, rng: np.random.Generator, fiber_rgb: np.ndarray | None = None
               ) -> np.ndarray:
        """One frame.

        Parameters
        ----------
        fiber_gain : ndarray, shape (N,), float
            Light of every fiber relative to rest (1 = rest, 0 = dark), layout order.
        rng : numpy.random.Generator
            Picks the slice of the noise bank.
        fiber_rgb : ndarray, shape (N, 3), optional
            RGB frames: each fiber's own channel gains (colour-coded fibers), instead of the optics' ``rgb_gains``
            for all.

        Returns
        -------
        ndarray, uint8, shape (H, W) or (H, W, 3)
            The frame, clipped to 0..255.
        """
        gain = np.asarray(fiber_gain, dtype=np.float32).reshape(-1)
        if gain.shape[0] != self.layout.n_fibers:
            raise ValueError(f"fiber_gain must have shape ({self.layout.n_fibers},)")
        if fiber_rgb is not None and self.optics.rgb:
            level = (gain * self._peak32)[self._fid] * self._weight
            tint = (np.asarray(fiber_rgb, dtype=np.float32) * self._tint)[self._fid]
            self._buf[self._pix] = self._base_pix + level[:, None] * tint
            self._last_gain = None
        else:
            self._write_fibers(gain)
        n = self._buf.size
        k = int(rng.integers(0, self._noise.size - n + 1))
        noise = self._noise[k : k + n].reshape(self.frame_shape)
        # the same rounded, saturated sum as cv2.add(..., dtype=CV_8U), which OpenCV 4.12 (LeRobot's pin) takes
        # 9 ms a 640x480 frame for (its mixed-depth path); addWeighted 0.1-0.2 ms on 4.12 and 5.0
        return cv2.addWeighted(self._buf.reshape(self.frame_shape), 1.0, noise, 1.0, 0.0, dtype=cv2.CV_8U)

    def _write_fibers(self, gain: np.ndarray) -> None:
        """Every face pixel of ``_buf`` for the fibers' light ``gain`` (float32): only those of the fibers whose
        light changed since the last frame when they are few (the others' pixels hold these very values)."""
        changed = None if self._last_gain is None else np.flatnonzero(gain != self._last_gain)
        if changed is None or 4 * changed.size > gain.size:
            level = (gain * self._peak32)[self._fid] * self._weight
            self._buf[self._pix] = self._base_pix + level[:, None] * self._tint
        elif changed.size:
            first, counts = self._starts[changed], self._starts[changed + 1] - self._starts[changed]
            at = np.repeat(first - np.cumsum(counts) + counts, counts) + np.arange(int(counts.sum()))
            level = (gain * self._peak32)[self._fid[at]] * self._weight[at]
            self._buf[self._pix[at]] = self._base_pix[at] + level[:, None] * self._tint
        self._last_gain = gain.copy()


@functools.lru_cache(maxsize=16)
def _face_pixels(xy_bytes: bytes, blur_sigma_px: float, fiber_diameter_mm: float, face_falloff: float, width: int,
                 height: int, proj: Projection) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Flat pixel index, fiber index and weight (peak 1) of every lit pixel (read-only arrays).

    The same for every renderer of one layout, lens and blur (a scenario makes several: kept, not rebuilt).
    """
    xy_mm = np.frombuffer(xy_bytes, dtype=np.float64).reshape(-1, 2)
    centres = proj.to_image(xy_mm)
    sigma = max(blur_sigma_px, 0.3)
    r_px = fiber_diameter_mm / 2.0 * proj.scale
    reach = r_px + 4.0 * sigma + 2.0
    lo = np.floor(centres.min(axis=0) - reach).astype(int)
    hi = np.ceil(centres.max(axis=0) + reach).astype(int)
    c0, r0 = np.maximum(lo, 0)
    c1, r1 = np.minimum(hi, (width - 1, height - 1))
    rows, cols = np.mgrid[r0 : r1 + 1, c0 : c1 + 1]
    rows, cols = rows.ravel(), cols.ravel()
    xy = proj.to_layout(np.stack([cols, rows], axis=1).astype(np.float64))
    dist_mm, fid = cKDTree(xy_mm).query(xy)
    d = dist_mm * proj.scale
    dome = 1.0 - face_falloff * np.minimum(d / r_px, 1.0) ** 2
    weight = dome * 0.5 * erfc((d - r_px) / (np.sqrt(2.0) * sigma))
    keep = weight > _MIN_WEIGHT
    order = np.argsort(fid[keep], kind="stable")  # by fiber (a pixel shows one fiber: the order is free)
    out = (rows[keep] * width + cols[keep]).astype(np.intp)[order], fid[keep].astype(np.intp)[order], \
        weight[keep].astype(np.float32)[order]
    for a in out:
        a.flags.writeable = False
    return out


def _stray_light(optics: CameraOptics) -> np.ndarray:
    """The stray light's gray levels over the background, shape (H * W,): soft discs."""
    h, w = optics.height, optics.width
    rows, cols = np.mgrid[0:h, 0:w]
    out = np.zeros((h, w), dtype=np.float32)
    for col, row, radius, gray in optics.stray_light:
        d = np.hypot(cols - col, rows - row)
        out += np.float32(gray) * (0.5 * erfc((d - radius) / np.sqrt(2.0))).astype(np.float32)
    return out.ravel()
