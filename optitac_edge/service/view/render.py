"""The view as one picture (OpenCV), laid out as the page is: the camera with the fiber map, the sensor's
axes and the contacts (and their legend); the surface with its axes and colour scale; the contacts; the
fibers' light with its scale and the dark and saturated levels; the figures.

Used by ``optitac-edge snapshot`` (a PNG for headless use) and the page's snapshot button; the page itself
draws the same layers in the browser (assets/app.js).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from optitac_edge.core.bundle import CalibrationBundle

# BGR
GREEN, RED, YELLOW, MAGENTA, WHITE, ORANGE = (80, 200, 80), (60, 60, 235), (0, 220, 240), (220, 60, 220), \
    (235, 235, 235), (0, 140, 255)
BACKGROUND, GREY, AXIS = (26, 23, 21), (150, 150, 150), (255, 210, 80)
FONT = cv2.FONT_HERSHEY_SIMPLEX
#: A fiber darker than this fraction of the median fiber is flagged dark; this bright (gray level) saturated.
DARK_FRACTION, SATURATED_LEVEL = 0.25, 250.0
#: The picture's parts, px.
CAMERA_SIDE, SURFACE_SIDE, LEVELS_HEIGHT, COLUMN = 760, 330, 130, 440


def _text(img: np.ndarray, text: str, at: tuple[int, int], colour: tuple[int, int, int] = WHITE,
          size: float = 0.5, outline: bool = False) -> None:
    """``text`` at ``at`` (its baseline's left), readable on any background with ``outline``."""
    if outline:
        cv2.putText(img, text, at, FONT, size, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, at, FONT, size, colour, 1, cv2.LINE_AA)


def _arrow(img: np.ndarray, a: np.ndarray, b: np.ndarray, label: str) -> None:
    pa, pb = (round(a[0]), round(a[1])), (round(b[0]), round(b[1]))
    cv2.arrowedLine(img, pa, pb, (0, 0, 0), 4, cv2.LINE_AA, tipLength=0.15)
    cv2.arrowedLine(img, pa, pb, AXIS, 2, cv2.LINE_AA, tipLength=0.15)
    d = (b - a) / max(float(np.hypot(*(b - a))), 1e-9)
    _text(img, label, (round(b[0] + 8 * d[0] - 8), round(b[1] + 8 * d[1] + 5)), AXIS, 0.55, outline=True)


def camera_panel(gray: np.ndarray, bundle: CalibrationBundle, contacts: Sequence[dict[str, Any]],
                 levels: np.ndarray | None) -> np.ndarray:
    """The camera frame around the fiber array, the fiber map, the sensor's +x and +y, the contacts."""
    t = bundle.fibers
    live = ~t.dead
    lo = t.centroid_px.min(axis=0) - 3 * float(np.median(np.sqrt(t.pixel_count / math.pi)))
    hi = t.centroid_px.max(axis=0) + 3 * float(np.median(np.sqrt(t.pixel_count / math.pi)))
    x0, y0 = max(int(lo[0]), 0), max(int(lo[1]), 0)
    x1, y1 = min(math.ceil(hi[0]), t.width), min(math.ceil(hi[1]), t.height)
    scale = CAMERA_SIDE / max(x1 - x0, y1 - y0, 1)
    crop = cv2.cvtColor(np.ascontiguousarray(gray[y0:y1, x0:x1]), cv2.COLOR_GRAY2BGR)
    img = cv2.resize(crop, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)

    def px(uv: np.ndarray) -> np.ndarray:
        return (np.asarray(uv, np.float64) - (x0, y0)) * scale

    radius = np.sqrt(t.pixel_count / math.pi) * scale
    median = float(np.median(levels[live])) if levels is not None and live.any() else 0.0
    show_ids = float(np.median(radius)) >= 9.0
    for k, (c, r) in enumerate(zip(px(t.centroid_px), radius)):
        centre = (round(c[0]), round(c[1]))
        if t.dead[k]:
            d = int(max(r, 3))
            cv2.line(img, (centre[0] - d, centre[1] - d), (centre[0] + d, centre[1] + d), RED, 2, cv2.LINE_AA)
            cv2.line(img, (centre[0] - d, centre[1] + d), (centre[0] + d, centre[1] - d), RED, 2, cv2.LINE_AA)
            continue
        warn = levels is not None and (levels[k] >= SATURATED_LEVEL or levels[k] < DARK_FRACTION * median)
        cv2.circle(img, centre, int(max(round(r), 2)), ORANGE if warn else GREEN, 2 if warn else 1, cv2.LINE_AA)
        if show_ids:
            label = str(int(bundle.layout.ids[k]))
            _text(img, label, (centre[0] - 4 * len(label), centre[1] + 4), WHITE, 0.36, outline=True)
    for u, v in px(t.unmatched_px.reshape(-1, 2)):
        cv2.drawMarker(img, (round(u), round(v)), YELLOW, cv2.MARKER_CROSS, 10, 2)
    reach = 0.45 * bundle.layout.radius_mm
    origin, ex, ey = px(bundle.transform.layout_to_image(np.array([[0.0, 0.0], [reach, 0.0], [0.0, reach]])))
    _arrow(img, origin, ex, "+x")
    _arrow(img, origin, ey, "+y")
    for c in contacts:
        pts = px(np.asarray(c["outline"])).round().astype(np.int32)
        cv2.polylines(img, [pts], True, MAGENTA, 2, cv2.LINE_AA)
        cu, cv = px(np.array([c["u"], c["v"]]))
        cv2.drawMarker(img, (round(cu), round(cv)), MAGENTA, cv2.MARKER_CROSS, 16, 2)
    legend = np.full((30, img.shape[1], 3), BACKGROUND, np.uint8)
    x = 8
    for colour, name in ((GREEN, "fiber"), (RED, "dead fiber"), (YELLOW, "unmatched blob"),
                         (ORANGE, "dark or saturated"), (MAGENTA, "contact"), (AXIS, "sensor axes")):
        cv2.rectangle(legend, (x, 9), (x + 12, 21), colour, 2)
        _text(legend, name, (x + 18, 20), WHITE, 0.45)
        x += 30 + 9 * len(name)
    return np.vstack([img, legend])


def _colour_scale(values: np.ndarray) -> np.ndarray:
    """Gray levels 0..255 as the view's surface colours (OpenCV's inferno)."""
    return cv2.applyColorMap(np.ascontiguousarray(values, dtype=np.uint8), cv2.COLORMAP_INFERNO)


def surface_panel(surface: np.ndarray, bundle: CalibrationBundle) -> np.ndarray:
    """The surface (+y up) with its mm axes and a colour scale of its values."""
    top = float(surface.max(initial=0.0))
    scaled = np.zeros(surface.shape, np.uint8) if top <= 0 else np.clip(surface / top * 255, 0, 255).astype(np.uint8)
    heat = cv2.resize(_colour_scale(np.flipud(scaled)), (SURFACE_SIDE, SURFACE_SIDE),
                      interpolation=cv2.INTER_NEAREST)
    g = bundle.grid
    extent = (g.n - 1) * g.step_mm

    def to_px(x_mm: float, y_mm: float) -> tuple[int, int]:
        return (round((x_mm - g.x0_mm) / extent * (SURFACE_SIDE - 1)),
                round((1 - (y_mm - g.y0_mm) / extent) * (SURFACE_SIDE - 1)))

    margin_l, margin_b, bar = 44, 34, 60
    panel = np.full((SURFACE_SIDE + margin_b + 24, margin_l + SURFACE_SIDE + bar + 40, 3), BACKGROUND, np.uint8)
    oy = 24
    panel[oy:oy + SURFACE_SIDE, margin_l:margin_l + SURFACE_SIDE] = heat
    _text(panel, f"Surface (max {top:.3g})", (margin_l, 17), WHITE, 0.55)
    half = math.floor(extent / 2 / 5) * 5 or round(extent / 2, 1)
    for v in (-half, 0.0, half):
        u, _ = to_px(v, g.y0_mm)
        cv2.line(panel, (margin_l + u, oy + SURFACE_SIDE), (margin_l + u, oy + SURFACE_SIDE + 5), GREY, 1)
        _text(panel, f"{v:g}", (margin_l + u - 8, oy + SURFACE_SIDE + 18), GREY, 0.4)
        _, w = to_px(g.x0_mm, v)
        cv2.line(panel, (margin_l - 5, oy + w), (margin_l, oy + w), GREY, 1)
        _text(panel, f"{v:g}", (4, oy + w + 4), GREY, 0.4)
    _text(panel, "x mm", (margin_l + SURFACE_SIDE - 40, oy + SURFACE_SIDE + 30), GREY, 0.4)
    o, ex, ey = to_px(0.0, 0.0), to_px(0.3 * extent, 0.0), to_px(0.0, 0.3 * extent)
    shift = np.array([margin_l, oy])
    _arrow(panel, np.array(o) + shift, np.array(ex) + shift, "+x")
    _arrow(panel, np.array(o) + shift, np.array(ey) + shift, "+y")
    bx = margin_l + SURFACE_SIDE + 14
    ramp = _colour_scale(np.linspace(255, 0, SURFACE_SIDE)[:, None].repeat(16, axis=1))
    panel[oy:oy + SURFACE_SIDE, bx:bx + 16] = ramp
    _text(panel, f"{top:.3g}", (bx + 20, oy + 10), GREY, 0.4)
    _text(panel, "0", (bx + 20, oy + SURFACE_SIDE), GREY, 0.4)
    _text(panel, "darkening", (bx - 6, oy + SURFACE_SIDE + 18), GREY, 0.4)
    return panel


def levels_panel(levels: np.ndarray | None, bundle: CalibrationBundle) -> np.ndarray:
    """Every fiber's gray level as a bar, with the 0-255 scale and the dark and saturated levels."""
    width = SURFACE_SIDE + 44 + 100
    panel = np.full((LEVELS_HEIGHT + 48, width, 3), BACKGROUND, np.uint8)
    _text(panel, "Fiber light (gray level)", (44, 17), WHITE, 0.55)
    oy, ox, w = 26, 44, SURFACE_SIDE

    def y_of(level: float) -> int:
        return oy + round((1 - level / 255.0) * LEVELS_HEIGHT)

    for level in (0, 128, 255):
        cv2.line(panel, (ox - 5, y_of(level)), (ox, y_of(level)), GREY, 1)
        _text(panel, str(level), (4, y_of(level) + 4), GREY, 0.4)
    if levels is None or not len(levels):
        return panel
    t = bundle.fibers
    live = ~t.dead
    median = float(np.median(levels[live])) if live.any() else 0.0
    dark = DARK_FRACTION * median
    bar = w / len(levels)
    for k, v in enumerate(levels):
        warn = not t.dead[k] and (v >= SATURATED_LEVEL or v < dark)
        colour = RED if t.dead[k] else ORANGE if warn else GREEN
        cv2.rectangle(panel, (ox + int(k * bar), y_of(float(v))), (ox + int((k + 1) * bar) - 1, y_of(0)), colour, -1)
    for mark, colour, name in ((SATURATED_LEVEL, RED, "saturated"), (dark, ORANGE, "dark")):
        cv2.line(panel, (ox, y_of(mark)), (ox + w, y_of(mark)), colour, 1, cv2.LINE_AA)
        _text(panel, f"{name} {mark:.0f}", (ox + w + 6, y_of(mark) + 4), colour, 0.4)
    _text(panel, f"fibers 1..{len(levels)}", (ox, oy + LEVELS_HEIGHT + 16), GREY, 0.4)
    return panel


def contacts_panel(contacts: Sequence[dict[str, Any]]) -> np.ndarray:
    """The contacts as the page's table."""
    rows = ["#  x, y (mm)      widths (mm)   angle  shape     strength"]
    fmt = (lambda v, d: "-" if v is None else f"{v:.{d}f}")
    for k, c in enumerate(contacts):
        rows.append(f"{k + 1}  {fmt(c.get('x_mm'), 2)}, {fmt(c.get('y_mm'), 2)}   "
                    f"{fmt(c.get('major_mm'), 2)} x {fmt(c.get('minor_mm'), 2)}   {fmt(c.get('angle_deg'), 0)}   "
                    f"{(c.get('shape') or '-'):8s}  {fmt(c.get('strength'), 0)}")
    if not contacts:
        rows.append("no contact")
    panel = np.full((30 + 20 * len(rows), COLUMN, 3), BACKGROUND, np.uint8)
    _text(panel, "Contacts", (8, 17), WHITE, 0.55)
    for k, row in enumerate(rows):
        _text(panel, row, (8, 38 + 20 * k), GREY if k == 0 else WHITE, 0.42)
    return panel


def _stack(parts: Sequence[np.ndarray], axis: int) -> np.ndarray:
    """``parts`` side by side (axis 1) or one under the other (axis 0), padded with the background."""
    size = max(p.shape[1 - axis] for p in parts)
    padded = []
    for p in parts:
        pad = size - p.shape[1 - axis]
        shape = (pad, p.shape[1], 3) if axis == 1 else (p.shape[0], pad, 3)
        padded.append(np.concatenate([p, np.full(shape, BACKGROUND, np.uint8)], axis=1 - axis) if pad else p)
    return np.concatenate(padded, axis=axis)


def render_view(gray: np.ndarray, bundle: CalibrationBundle, surface: np.ndarray, contacts: Sequence[dict[str, Any]],
                lines: Sequence[str], levels: np.ndarray | None = None) -> np.ndarray:
    """The view picture.

    Parameters
    ----------
    gray : ndarray, shape (H, W), uint8
        The camera frame's gray levels.
    bundle : CalibrationBundle
        Its fiber map (outlines, ids, dead fibers, unmatched blobs), transform and surface grid.
    surface : ndarray, shape (n, n), float32
        The truncated inverted surface (row 0 at the grid's lowest y).
    contacts : sequence of dict
        Each with ``u``, ``v`` (centroid, px), ``outline`` (ellipse points, px) and the estimate's fields.
    lines : sequence of str
        Figures printed at the top (fps, drops, link...).
    levels : ndarray, shape (N,), optional
        The fibers' gray levels: dark and saturated fibers are ringed, and drawn as bars.

    Returns
    -------
    ndarray, shape (H', W', 3), uint8
        BGR picture.
    """
    left = camera_panel(gray, bundle, contacts, levels)
    right = _stack([surface_panel(surface, bundle), contacts_panel(contacts), levels_panel(levels, bundle)], axis=0)
    body = _stack([left, np.full((left.shape[0], 16, 3), BACKGROUND, np.uint8), right], axis=1)
    header = np.full((22 * max(len(lines), 1) + 12, body.shape[1], 3), BACKGROUND, np.uint8)
    _text(header, "optitac-edge", (8, 22), WHITE, 0.6)
    for k, line in enumerate(lines):
        _text(header, line, (140, 22 * (k + 1)), WHITE, 0.5)
    return _stack([header, body], axis=0)


def encode_png(picture: np.ndarray) -> bytes:
    """PNG bytes of a BGR picture."""
    ok, data = cv2.imencode(".png", picture)
    if not ok:
        raise ValueError("PNG encoding failed")
    return bytes(data.tobytes())


@dataclass(frozen=True)
class Published:
    """One update of the live view as the server hands it out (immutable once published)."""

    seq: int
    state: bytes  # JSON
    jpeg: bytes
    surface: np.ndarray  # (n, n) float32, for the snapshot picture
    gray: np.ndarray
    contacts: list[dict[str, Any]]
    levels: np.ndarray


def render_published(p: Published, bundle: CalibrationBundle) -> np.ndarray:
    """The picture of one view update (:class:`Published`), with its figures."""
    import json

    s = json.loads(p.state)
    lines = [(f"{s['fps']:.1f} fps  frames {s['frames']}  dropped {s['frames_dropped']}  camera faults "
              f"{s['camera_errors']}  light changes {s['light_changes']}  link {s['link']}"),
             (f"contacts {len(s['contacts'])}  truncation {s['truncation']:g}  dark fibers {len(s['dark'])}  "
              f"saturated fibers {len(s['saturated'])}")]
    return render_view(p.gray, bundle, p.surface, p.contacts, lines, p.levels)
