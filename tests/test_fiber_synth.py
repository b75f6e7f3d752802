"""A small synthetic rest-frame renderer for the fiber-map tests (and its own sanity test).

Independent of :mod:`optitac_edge.sim`: hex layout -> mirror/rotate/scale ->
Brown distortion (k1, k2, tangential p1, p2, deliberately not the k1-only model
the registration fits) -> discs with per-fiber brightness spread, vignetting,
blur and noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from optitac_edge.core.layout import FiberLayout, hex_layout


@dataclass(frozen=True)
class Synth:
    width: int = 640
    height: int = 480
    rotation_deg: float = 0.0
    mirror: bool = False
    fill: float = 0.85  # array diameter / image height
    k1: float = -0.04
    k2: float = 0.01
    p1: float = 0.003
    p2: float = -0.002
    dark_fibers: tuple[int, ...] = ()
    dark_level: float = 0.05
    spread: float = 0.15
    vignetting: float = 0.25
    noise: float = 4.0
    background: float = 12.0
    peak: float = 200.0
    offset_px: tuple[float, float] = (7.0, -5.0)
    face_mm: float = 1.0
    blur_px: float = 0.0  # 0: automatic


def true_centres(s: Synth, layout: FiberLayout | None = None) -> tuple[np.ndarray, float]:
    """True fiber centres (N, 2) (col, row) px and the scale px/mm."""
    layout = layout or hex_layout()
    scale = s.fill * s.height / (2.0 * layout.radius_mm + 1.0)
    xy = layout.xy_mm.copy()
    if s.mirror:
        xy[:, 0] = -xy[:, 0]
    t = math.radians(s.rotation_deg)
    c, sn = math.cos(t), math.sin(t)
    xr, yr = c * xy[:, 0] - sn * xy[:, 1], sn * xy[:, 0] + c * xy[:, 1]
    # Normalised coordinates (relative to the array radius in px), image axes.
    rr = scale * layout.radius_mm
    x, y = xr * scale / rr, -yr * scale / rr
    r2 = x * x + y * y
    radial = 1 + s.k1 * r2 + s.k2 * r2 * r2
    xd = x * radial + 2 * s.p1 * x * y + s.p2 * (r2 + 2 * x * x)
    yd = y * radial + s.p1 * (r2 + 2 * y * y) + 2 * s.p2 * x * y
    cx = s.width / 2.0 + s.offset_px[0]
    cy = s.height / 2.0 + s.offset_px[1]
    return np.stack([cx + xd * rr, cy + yd * rr], axis=1), scale


def render(s: Synth, seed: int = 0, n_frames: int = 1) -> np.ndarray:
    """Rest frames, shape (n_frames, H, W), uint8."""
    rng = np.random.default_rng(seed)
    centres, scale = true_centres(s)
    n = centres.shape[0]
    gain = 1.0 + s.spread * rng.uniform(-1, 1, n)
    gain[list(s.dark_fibers)] = s.dark_level
    rad = np.hypot(centres[:, 0] - s.width / 2, centres[:, 1] - s.height / 2) / (s.height / 2)
    gain *= 1.0 - s.vignetting * np.clip(rad, 0, 1.2) ** 2
    ss = 4  # supersampling for anti-aliased discs
    canvas = np.zeros((s.height * ss, s.width * ss), dtype=np.float32)
    r_px = 0.5 * s.face_mm * scale * ss
    for (u, v), g in zip(centres, gain):
        cv2.circle(canvas, (round(float(u * ss)), round(float(v * ss))), round(float(r_px)), float(g), -1)
    img = cv2.resize(canvas, (s.width, s.height), interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), s.blur_px or max(0.6, 0.04 * scale))
    base = s.background + s.peak * img
    frames = base[None] + s.noise * rng.standard_normal((n_frames, s.height, s.width))
    return np.clip(np.rint(frames), 0, 255).astype(np.uint8)


def test_renderer_draws_discs() -> None:
    frames = render(Synth(), n_frames=2)
    assert frames.shape == (2, 480, 640) and frames.dtype == np.uint8
    centres, _ = true_centres(Synth())
    u, v = np.rint(centres[108]).astype(int)
    assert frames[0, v, u] > 150 and np.median(frames[0]) < 40
