"""Built-in simulated recordings with ground truth.

Every recording starts with :data:`REST_FRAMES` contact-free frames; each press
is then held for :data:`HOLD_FRAMES` frames at full depth, followed by one
contact-free frame. ``truth.csv`` has a row for every frame. Scenarios:

``rest``     contact-free frames only (default 30 frames).
``demo``     random presses: random shape, angle, size 3-10 mm (edge width
             1.5-3 mm), depth 1.5-3.5 mm, fully on the array, i.e. the outline
             within the array's inscribed circle (default 300 frames).
``seen``     5 mm circle, 3 mm deep, over every fiber in layout order.
``unseen``   5 mm circle, 3 mm deep, in 0.25 mm steps along x (y = 0), then
             along y (x = 0), as far as it stays 0.5 mm inside the array (+-9 mm).
``repeat``   5 mm circle, 3 mm deep, 10 presses at each of 5 points (the centre
             and 6 mm out at 45, 135, 225, 315 degrees), +-0.05 mm uniform jitter.
``widths``   circles of :data:`WIDTHS_MM` diameters, 3 mm deep, 5 presses each
             at random positions fully on the array (at the centre when the
             circle could move less than a quarter of the inscribed radius).
``shapes``   40 presses of each shape in random order, random angle and
             position fully on the array, size 4-8 mm (edge width 1.5-2 mm), 3 mm deep.

Angles are drawn within each shape's symmetry period (circle 0; square
[0, 90); triangle [0, 120); ellipse and edge [0, 180)). ``seed`` controls
positions, sizes and frame noise; the physical sensor (fiber transmission,
fixed-pattern noise) is set by ``sensor_seed``, the same by default in every
scenario so that recordings of different seeds come from the same sensor.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull

from ..layout import FiberLayout, hex_layout
from ..recording import SHAPES, RecordingMeta, RecordingWriter
from .optics import DEFAULT_OPTICS, CameraOptics
from .render import SENSOR_SEED
from .sensor import SimulatedSensor
from .skin import DEFAULT_SKIN, Indenter, SkinModel, bounding_radius

log = logging.getLogger(__name__)

SCENARIOS: tuple[str, ...] = ("rest", "demo", "seen", "unseen", "repeat", "widths", "shapes")
REST_FRAMES = 10
HOLD_FRAMES = 2
FPS = 60.0
WIDTHS_MM: tuple[float, ...] = tuple(float(d) for d in np.round(np.linspace(1.85, 20.09, 12), 2))
ANGLE_PERIOD_DEG = {
    "circle": 0.0,
    "square": 90.0,
    "triangle": 120.0,
    "ellipse": 180.0,
    "edge": 180.0,
}

#: The contact of one frame: an indenter or None (contact-free).
Frame = Indenter | None


def inscribed_radius(layout: FiberLayout) -> float:
    """Radius (mm) of the largest origin-centred circle inside the fiber centres' convex hull."""
    offsets = ConvexHull(layout.xy_mm).equations[:, 2]  # n . p + offset <= 0 inside, |n| = 1
    return float(-offsets.max())


def _place(
    rng: np.random.Generator,
    shape: str,
    size: float,
    depth: float,
    layout: FiberLayout,
    skin: SkinModel,
) -> Indenter:
    """An indenter at a random angle and position with its outline inside the array."""
    angle = float(rng.uniform(0.0, ANGLE_PERIOD_DEG[shape])) if ANGLE_PERIOD_DEG[shape] else 0.0
    probe = Indenter(shape, 0.0, 0.0, angle, size, depth)
    inner = inscribed_radius(layout)
    room = inner - bounding_radius(probe, skin)
    if room < inner / 4:
        return probe
    r, t = room * math.sqrt(rng.uniform()), rng.uniform(0.0, 2 * math.pi)
    return Indenter(shape, r * math.cos(t), r * math.sin(t), angle, size, depth)


def _demo(rng: np.random.Generator, layout: FiberLayout, skin: SkinModel, n: int) -> list[Indenter]:
    out = []
    for _ in range(n):
        shape = str(rng.choice(SHAPES))
        size = rng.uniform(1.5, 3.0) if shape == "edge" else rng.uniform(3.0, 10.0)
        out.append(_place(rng, shape, float(size), float(rng.uniform(1.5, 3.5)), layout, skin))
    return out


def _seen(rng: np.random.Generator, layout: FiberLayout, skin: SkinModel, n: int) -> list[Indenter]:
    return [Indenter("circle", float(x), float(y), 0.0, 5.0, 3.0) for x, y in layout.xy_mm]


def _unseen(
    rng: np.random.Generator, layout: FiberLayout, skin: SkinModel, n: int
) -> list[Indenter]:
    step = 0.25
    lim = math.floor((layout.radius_mm - 2.5 - 0.5) / step + 1e-9) * step
    line = np.arange(-lim, lim + step / 2, step)
    return [Indenter("circle", float(v), 0.0, 0.0, 5.0, 3.0) for v in line] + [
        Indenter("circle", 0.0, float(v), 0.0, 5.0, 3.0) for v in line
    ]


def _repeat(
    rng: np.random.Generator, layout: FiberLayout, skin: SkinModel, n: int
) -> list[Indenter]:
    ring = 0.5 * layout.radius_mm
    angles = np.radians([45.0, 135.0, 225.0, 315.0])
    points = [(0.0, 0.0), *zip(ring * np.cos(angles), ring * np.sin(angles))]
    out = []
    for px, py in points:
        for _ in range(10):
            jx, jy = rng.uniform(-0.05, 0.05, 2)
            out.append(Indenter("circle", float(px + jx), float(py + jy), 0.0, 5.0, 3.0))
    return out


def _widths(
    rng: np.random.Generator, layout: FiberLayout, skin: SkinModel, n: int
) -> list[Indenter]:
    return [_place(rng, "circle", d, 3.0, layout, skin) for d in WIDTHS_MM for _ in range(5)]


def _shapes(
    rng: np.random.Generator, layout: FiberLayout, skin: SkinModel, n: int
) -> list[Indenter]:
    order = rng.permutation(np.repeat(np.arange(len(SHAPES)), 40))
    out = []
    for k in order:
        shape = SHAPES[k]
        size = rng.uniform(1.5, 2.0) if shape == "edge" else rng.uniform(4.0, 8.0)
        out.append(_place(rng, shape, float(size), 3.0, layout, skin))
    return out


_PressMaker = Callable[[np.random.Generator, FiberLayout, SkinModel, int], list[Indenter]]
_PRESSES: dict[str, _PressMaker] = {
    "demo": _demo,
    "seen": _seen,
    "unseen": _unseen,
    "repeat": _repeat,
    "widths": _widths,
    "shapes": _shapes,
}
_DEFAULT_FRAMES = {"rest": 30, "demo": 300}


def schedule(
    name: str,
    seed: int = 0,
    frames: int | None = None,
    layout: FiberLayout | None = None,
    skin: SkinModel = DEFAULT_SKIN,
) -> list[Frame]:
    """The contact of every frame of scenario ``name`` (None = contact-free).

    ``frames`` sets the length of ``rest`` and ``demo`` (defaults 30, 300) and
    truncates the others (default: all their presses).

    Raises
    ------
    ValueError
        Unknown scenario, or ``frames`` < :data:`REST_FRAMES`.
    """
    if name not in SCENARIOS:
        raise ValueError(f"unknown scenario {name!r}; expected one of {SCENARIOS}")
    if frames is not None and frames < REST_FRAMES:
        raise ValueError(f"a recording needs at least {REST_FRAMES} frames")
    layout = hex_layout() if layout is None else layout
    n_frames = frames if frames is not None else _DEFAULT_FRAMES.get(name)
    n_presses = 0 if n_frames is None else -(-(n_frames - REST_FRAMES) // (HOLD_FRAMES + 1))
    rng = np.random.default_rng([seed, 10])
    presses = _PRESSES[name](rng, layout, skin, n_presses) if name != "rest" else []
    out: list[Frame] = [None] * REST_FRAMES
    for press in presses:
        out += [press] * HOLD_FRAMES + [None]
    if n_frames is not None:
        out = (out + [None] * n_frames)[:n_frames]
    return out


def write_scenario(
    out_dir: str | Path,
    name: str,
    seed: int = 0,
    frames: int | None = None,
    optics: CameraOptics = DEFAULT_OPTICS,
    skin: SkinModel = DEFAULT_SKIN,
    layout: FiberLayout | None = None,
    sensor_seed: int = SENSOR_SEED,
) -> Path:
    """Simulate scenario ``name`` and stream it into the recording directory ``out_dir``.

    Parameters
    ----------
    out_dir : path-like
        Recording directory to create (or overwrite); the recording is written
        directly into it.
    name : str
        One of :data:`SCENARIOS`.
    seed : int
        Positions, sizes, angles and frame noise (default 0).
    frames : int or None
        Length of ``rest`` / ``demo``; truncation of the others (see :func:`schedule`).
    optics, skin, layout
        The simulated camera, skin and fiber layout (default hex_layout()).
    sensor_seed : int
        The physical sensor's randomness (default :data:`SENSOR_SEED`, the same
        sensor for every scenario and seed).

    Returns
    -------
    Path
        ``out_dir``. ``meta.json`` holds ``rest_frames``, ``fps`` and a
        ``simulator`` object: scenario, seed, sensor_seed, optics, skin,
        scale_px_per_mm, centre_px, rest_peak_gray and ``fiber_centres_px``
        (N x [col, row], layout order: the ground truth of the fiber map).
    """
    layout = hex_layout() if layout is None else layout
    plan = schedule(name, seed, frames, layout, skin)
    sensor = SimulatedSensor(layout, optics, skin, seed=seed, sensor_seed=sensor_seed)
    proj = sensor.renderer.projection
    extra = {
        "simulator": {
            "scenario": name,
            "seed": seed,
            "sensor_seed": sensor_seed,
            "optics": optics.to_dict(),
            "skin": skin.to_dict(),
            "scale_px_per_mm": proj.scale,
            "centre_px": [proj.cx, proj.cy],
            "rest_peak_gray": np.round(sensor.rest_peak, 3).tolist(),
            "fiber_centres_px": np.round(sensor.fiber_centres_px, 4).tolist(),
        }
    }
    meta = RecordingMeta(rest_frames=REST_FRAMES, fps=FPS, extra=extra)
    out = Path(out_dir)
    log.info(
        "simulating %s (seed %d): %d frames of %s into %s",
        name,
        seed,
        len(plan),
        sensor.frame_shape,
        out,
    )
    rest = np.zeros(layout.n_fibers)
    with RecordingWriter(out, len(plan), sensor.frame_shape, meta, with_truth=True) as writer:
        last: Frame = None
        dark = rest
        for i, press in enumerate(plan):
            if press is not last:
                dark = rest if press is None else sensor.darkening([press])
                last = press
            writer.write(i, sensor.frame_from_darkening(dark))
            if press is None:
                writer.write_truth(i, False)
            else:
                writer.write_truth(
                    i,
                    True,
                    press.shape,
                    press.x_mm,
                    press.y_mm,
                    press.angle_deg,
                    press.size_mm,
                    press.depth_mm,
                )
    return out
