"""The view as one picture (OpenCV): the camera frame with the fiber map and contacts, the surface, the figures.

Used by ``optitac-edge snapshot`` (a PNG for headless use) and the page's
snapshot button; the page itself draws the same layers in the browser.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import cv2
import numpy as np

from optitac_edge.core.bundle import CalibrationBundle

GREEN, RED, YELLOW, MAGENTA, WHITE, ORANGE = (80, 200, 80), (60, 60, 235), (0, 220, 240), (220, 60, 220), \
    (235, 235, 235), (0, 140, 255)


def render_view(gray: np.ndarray, bundle: CalibrationBundle, surface: np.ndarray, contacts: Sequence[dict[str, Any]],
                lines: Sequence[str], levels: np.ndarray | None = None) -> np.ndarray:
    """The view picture.

    Parameters
    ----------
    gray : ndarray, shape (H, W), uint8
        The camera frame's gray levels.
    bundle : CalibrationBundle
        Its fiber map (outlines, ids, dead fibers, unmatched blobs) and surface grid.
    surface : ndarray, shape (n, n), float32
        The truncated inverted surface (row 0 at the grid's lowest y).
    contacts : sequence of dict
        Each with ``u``, ``v`` (centroid, px), ``outline`` (ellipse points, px) and the estimate's fields.
    lines : sequence of str
        Figures printed under the picture (fps, drops, link...).
    levels : ndarray, shape (N,), optional
        The fibers' gray levels: dark and saturated fibers are ringed.

    Returns
    -------
    ndarray, shape (H', W', 3), uint8
        BGR picture.
    """
    t = bundle.fibers
    img = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    scale = max(1, math.ceil(1200 / max(img.shape[:2])))  # fiber ids need ~20 px a fiber
    if scale > 1:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    radius = np.sqrt(t.pixel_count / math.pi) * scale
    live = ~t.dead
    median = float(np.median(levels[live])) if levels is not None and live.any() else 0.0
    show_ids = float(np.median(radius)) >= 9.0
    for k, (c, r) in enumerate(zip(t.centroid_px * scale, radius)):
        centre = (round(c[0]), round(c[1]))
        if t.dead[k]:
            d = int(max(r, 3))
            cv2.line(img, (centre[0] - d, centre[1] - d), (centre[0] + d, centre[1] + d), RED, 1, cv2.LINE_AA)
            cv2.line(img, (centre[0] - d, centre[1] + d), (centre[0] + d, centre[1] - d), RED, 1, cv2.LINE_AA)
            continue
        colour = GREEN
        if levels is not None and (levels[k] >= 250 or levels[k] < 0.25 * median):
            colour = ORANGE
        cv2.circle(img, centre, int(max(round(r), 2)), colour, 1, cv2.LINE_AA)
        if show_ids:
            label = str(int(bundle.layout.ids[k]))
            cv2.putText(img, label, (centre[0] - 3 * len(label), centre[1] + 3),
                        cv2.FONT_HERSHEY_PLAIN, 0.6, WHITE, 1, cv2.LINE_AA)
    for u, v in t.unmatched_px * scale:
        cv2.drawMarker(img, (round(u), round(v)), YELLOW, cv2.MARKER_CROSS, 8, 1)
    for c in contacts:
        pts = (np.asarray(c["outline"]) * scale).round().astype(np.int32)
        cv2.polylines(img, [pts], True, MAGENTA, 2, cv2.LINE_AA)
        cv2.drawMarker(img, (round(c["u"] * scale), round(c["v"] * scale)), MAGENTA,
                       cv2.MARKER_CROSS, 14, 2)
    h = img.shape[0]
    top = float(surface.max(initial=0.0))
    scaled = np.zeros(surface.shape, np.uint8) if top <= 0 else np.clip(surface / top * 255, 0, 255).astype(np.uint8)
    heat = cv2.resize(cv2.applyColorMap(np.ascontiguousarray(np.flipud(scaled)), cv2.COLORMAP_INFERNO), (h, h),
                      interpolation=cv2.INTER_NEAREST)
    cv2.putText(heat, f"surface max {top:.3g}", (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, WHITE, 1, cv2.LINE_AA)
    picture = np.hstack([img, heat])
    text = np.zeros((22 * max(len(lines), 1) + 8, picture.shape[1], 3), np.uint8)
    for k, line in enumerate(lines):
        cv2.putText(text, line, (8, 22 * (k + 1)), cv2.FONT_HERSHEY_SIMPLEX, 0.5, WHITE, 1, cv2.LINE_AA)
    return np.vstack([picture, text])


def encode_png(picture: np.ndarray) -> bytes:
    """PNG bytes of a BGR picture."""
    ok, data = cv2.imencode(".png", picture)
    if not ok:
        raise ValueError("PNG encoding failed")
    return bytes(data.tobytes())


def render_published(p: Any, bundle: CalibrationBundle) -> np.ndarray:
    """The picture of one view update (:class:`~optitac_edge.service.view.live.Published`), with its figures."""
    import json

    s = json.loads(p.state)
    lines = [(f"{s['fps']:.1f} fps  frames {s['frames']}  dropped {s['frames_dropped']}  camera faults "
              f"{s['camera_errors']}  light changes {s['light_changes']}  link {s['link']}"),
             (f"contacts {len(s['contacts'])}  truncation {s['truncation']:g}  dark fibers {len(s['dark'])}  "
              f"saturated fibers {len(s['saturated'])}")]
    return render_view(p.gray, bundle, p.surface, p.contacts, lines, p.levels)
