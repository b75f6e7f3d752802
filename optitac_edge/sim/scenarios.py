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
``depths``   depth and force calibration (the bring-up experiment of that name):
             a 5 mm circle at the centre and at 6 points half the array's radius
             out (every 60 degrees), at each of :data:`DEPTHS_MM`, twice, in random
             order; ``truth.csv`` ends with the load cell's ``force_n`` (the
             simulator's force model at the press's real depth, see
             :func:`~optitac_edge.sim.skin.contact_force_n`).
``snapshots`` an hour of snapshots 20 s apart, presses of known force at random places and depths
             and the skin at rest, the baseline taken again every 5 minutes
             (:mod:`optitac_edge.sim.snapshots`).
``drift``    baseline tracking: long contact-free stretches with the LEDs warming
             up (+:data:`DRIFT_WARMUP` brightness over the recording, per-fiber
             drift of sigma :data:`DRIFT_FIBER_SIGMA`) and an occasional press:
             after the rest frames, :data:`DRIFT_GAP` contact-free frames then a
             random press (as ``demo``, 3 mm deep) held :data:`DRIFT_HOLD`
             frames, repeated (default 1200 frames = 20 s).

Sizes, steps and margins are the paper's, for its 1.5 mm array; a layout of another pitch scales them
(:func:`~optitac_edge.core.layout.scaled_mm`), and its skin and end faces (:mod:`~optitac_edge.sim.arrays`).

Angles are drawn within each shape's symmetry period (circle 0; square
[0, 90); triangle [0, 120); ellipse and edge [0, 180)). ``seed`` controls
positions, sizes and frame noise; the physical sensor (fiber transmission,
fixed-pattern noise) is set by ``sensor_seed``, the same by default in every
scenario so that recordings of different seeds come from the same sensor.

``day`` (see :class:`~optitac_edge.sim.drift.SessionDrift`) and ``variant``
(see :func:`~optitac_edge.sim.drift.sensor_variant`) select the recording
session and the simulated sensor; both 0 by default (the nominal sensor).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull

from optitac_edge.core.fiber_table import FiberTable
from optitac_edge.core.layout import FiberLayout, hex_layout, pitch_scale, scaled_mm
from optitac_edge.core.reach import depth_points, unseen_line
from optitac_edge.io.recording import LAYOUT_KEY, SHAPES, RecordingMeta, layout_meta
from optitac_edge.io.recording_writer import RecordingWriter
from optitac_edge.sim.arrays import optics_for, skin_for
from optitac_edge.sim.drift import SessionDrift, sensor_variant, variant_sensor_seed
from optitac_edge.sim.motion_scenarios import DEPTH_MM as MOTION_DEPTH_MM
from optitac_edge.sim.motion_scenarios import (
    MOTION_FPS,
    MOTION_REST_FRAMES,
    MOTION_SCENARIOS,
    MotionFrame,
    motion_schedule,
    press_depth_factors,
    real_indenter,
)
from optitac_edge.sim.optics import DEFAULT_OPTICS, CameraOptics
from optitac_edge.sim.patches import PatchPlacement
from optitac_edge.sim.physics import physics as physics_named
from optitac_edge.sim.real import FiberColours, WanderingLight
from optitac_edge.sim.sensor import SimulatedSensor
from optitac_edge.sim.skin import (
    DEFAULT_SKIN,
    Indenter,
    SkinModel,
    bounding_radius,
    clamp_radius_mm,
    contact_force_n,
)
from optitac_edge.sim.snapshots import LEAD_FRAMES, SNAPSHOT_SCENARIOS, Snapshot, snapshot_session

log = logging.getLogger(__name__)

SCENARIOS: tuple[str, ...] = (
    "rest",
    "demo",
    "seen",
    "unseen",
    "repeat",
    "widths",
    "shapes",
    "drift",
    "depths",
)
REST_FRAMES = 10
HOLD_FRAMES = 2
FPS = 60.0
#: ``drift`` scenario: contact-free frames before each press, frames each press is held,
#: relative LED brightening over the whole recording, per-fiber drift sigma over it.
DRIFT_GAP = 90
DRIFT_HOLD = 30
DRIFT_WARMUP = 0.03
DRIFT_FIBER_SIGMA = 0.005
#: ``depths`` scenario: the commanded depths, mm (the bring-up experiment's, ``bringup.experiments``: a
#: test keeps the two the same; the simulator sits below bring-up and cannot import it).
DEPTHS_MM: tuple[float, ...] = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0)
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
    k = pitch_scale(layout)
    out = []
    for _ in range(n):
        shape = str(rng.choice(SHAPES))
        size = rng.uniform(1.5, 3.0) if shape == "edge" else rng.uniform(3.0, 10.0)
        out.append(_place(rng, shape, float(size) * k, float(rng.uniform(1.5, 3.5)), layout, skin))
    return out


def _circle(layout: FiberLayout) -> float:
    """The experiments' circle: 5 mm on the paper's array."""
    return scaled_mm(5.0, pitch_scale(layout))


def _seen(rng: np.random.Generator, layout: FiberLayout, skin: SkinModel, n: int) -> list[Indenter]:
    size = _circle(layout)
    return [Indenter("circle", float(x), float(y), 0.0, size, 3.0) for x, y in layout.xy_mm]


def _unseen(
    rng: np.random.Generator, layout: FiberLayout, skin: SkinModel, n: int
) -> list[Indenter]:
    k, size = pitch_scale(layout), _circle(layout)
    step = scaled_mm(0.25, k)
    x_line, y_line = (unseen_line(layout, axis, size, step, k) for axis in (0, 1))
    return [Indenter("circle", float(v), 0.0, 0.0, size, 3.0) for v in x_line] + [
        Indenter("circle", 0.0, float(v), 0.0, size, 3.0) for v in y_line
    ]


def _repeat(
    rng: np.random.Generator, layout: FiberLayout, skin: SkinModel, n: int
) -> list[Indenter]:
    ring, size, jitter = 0.5 * layout.radius_mm, _circle(layout), scaled_mm(0.05, pitch_scale(layout))
    angles = np.radians([45.0, 135.0, 225.0, 315.0])
    points = [(0.0, 0.0), *zip(ring * np.cos(angles), ring * np.sin(angles))]
    out = []
    for px, py in points:
        for _ in range(10):
            jx, jy = rng.uniform(-jitter, jitter, 2)
            out.append(Indenter("circle", float(px + jx), float(py + jy), 0.0, size, 3.0))
    return out


def _drift(
    rng: np.random.Generator, layout: FiberLayout, skin: SkinModel, n: int
) -> list[Indenter]:
    k = pitch_scale(layout)
    out = []
    for _ in range(n):
        shape = str(rng.choice(SHAPES))
        size = rng.uniform(1.5, 3.0) if shape == "edge" else rng.uniform(3.0, 10.0)
        out.append(_place(rng, shape, float(size) * k, 3.0, layout, skin))
    return out


def _widths(
    rng: np.random.Generator, layout: FiberLayout, skin: SkinModel, n: int
) -> list[Indenter]:
    k = pitch_scale(layout)
    return [_place(rng, "circle", scaled_mm(d, k), 3.0, layout, skin) for d in WIDTHS_MM for _ in range(5)]


def _shapes(
    rng: np.random.Generator, layout: FiberLayout, skin: SkinModel, n: int
) -> list[Indenter]:
    k = pitch_scale(layout)
    order = rng.permutation(np.repeat(np.arange(len(SHAPES)), 40))
    out = []
    for i in order:
        shape = SHAPES[i]
        size = rng.uniform(1.5, 2.0) if shape == "edge" else rng.uniform(4.0, 8.0)
        out.append(_place(rng, shape, float(size) * k, 3.0, layout, skin))
    return out


def _depths(
    rng: np.random.Generator, layout: FiberLayout, skin: SkinModel, n: int
) -> list[Indenter]:
    size = _circle(layout)
    presses = [Indenter("circle", px, py, 0.0, size, d)
               for px, py in depth_points(layout) for d in DEPTHS_MM for _ in range(2)]
    return [presses[i] for i in rng.permutation(len(presses))]


_PressMaker = Callable[[np.random.Generator, FiberLayout, SkinModel, int], list[Indenter]]
_PRESSES: dict[str, _PressMaker] = {
    "demo": _demo,
    "seen": _seen,
    "unseen": _unseen,
    "repeat": _repeat,
    "widths": _widths,
    "shapes": _shapes,
    "drift": _drift,
    "depths": _depths,
}
_DEFAULT_FRAMES = {"rest": 30, "demo": 300, "drift": 1200}


def schedule(
    name: str,
    seed: int = 0,
    frames: int | None = None,
    layout: FiberLayout | None = None,
    skin: SkinModel = DEFAULT_SKIN,
) -> list[Frame]:
    """The contact of every frame of scenario ``name`` (None = contact-free).

    ``frames`` sets the length of ``rest``, ``demo`` and ``drift`` (defaults 30,
    300, 1200) and truncates the others (default: all their presses).

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
    period = DRIFT_GAP + DRIFT_HOLD if name == "drift" else HOLD_FRAMES + 1
    n_presses = 0 if n_frames is None else -(-(n_frames - REST_FRAMES) // period)
    rng = np.random.default_rng([seed, 10])
    presses = _PRESSES[name](rng, layout, skin, n_presses) if name != "rest" else []
    out: list[Frame] = [None] * REST_FRAMES
    for press in presses:
        if name == "drift":
            out += [None] * DRIFT_GAP + [press] * DRIFT_HOLD
        else:
            out += [press] * HOLD_FRAMES + [None]
    if n_frames is not None:
        out = (out + [None] * n_frames)[:n_frames]
    return out


def scenario_drift(
    name: str, drift: SessionDrift, n_frames: int, warmup: float = DRIFT_WARMUP, fps: float = FPS
) -> SessionDrift:
    """The drift a recording of scenario ``name`` is made with.

    ``drift`` itself, except for the ``drift`` scenario, which imposes its LED
    warm-up (brightness x (1 + ``warmup``) from the first to the last frame;
    negative: the LEDs dim) and per-fiber drift (sigma :data:`DRIFT_FIBER_SIGMA`
    over the recording), keeping the day's other drift; and ``snapshots``, an hour
    long, which keeps the day's gains but not its within-recording ramps (made for
    seconds, they would run away; the ``real`` physics' wander is its slow drift).
    """
    if name == "snapshots":
        return replace(drift, led_drift_per_s=0.0, fiber_drift_per_s=0.0)
    if name not in ("drift", "hold"):
        return drift
    duration = max(n_frames - 1, 1) / fps
    return replace(
        drift,
        led_drift_per_s=warmup / duration,
        fiber_drift_per_s=DRIFT_FIBER_SIGMA / duration,
    )


def _find_fibers(layout: FiberLayout, optics: CameraOptics) -> Callable[[np.ndarray, str], FiberTable]:
    """The fibers of a simulated recording's rest frames, as ``calibrate fibers`` finds them with the
    orientation hint ``sim`` prints."""
    from optitac_edge.calibration.fibers import calibrate_fibers

    def find(rest: np.ndarray, pixel_format: str) -> FiberTable:
        return calibrate_fibers(rest, pixel_format, layout=layout, rotation_hint_deg=optics.rotation_deg,
                                mirror=optics.mirror).fibers

    return find


def write_scenario(  # noqa: PLR0913
    out_dir: str | Path,
    name: str,
    seed: int = 0,
    frames: int | None = None,
    optics: CameraOptics = DEFAULT_OPTICS,
    skin: SkinModel | None = None,
    layout: FiberLayout | None = None,
    sensor_seed: int | None = None,
    day: int = 0,
    variant: int = 0,
    drift: SessionDrift | None = None,
    warmup: float = DRIFT_WARMUP,
    patch: PatchPlacement | None = None,
    fresh: bool = False,
    storage: str = "raw",
    physics: str = "default",
) -> Path:
    """Simulate scenario ``name`` and stream it into the recording directory ``out_dir``.

    Parameters
    ----------
    out_dir : path-like
        Recording directory to create; a complete recording there is refused
        unless ``fresh`` (then replaced once the new one is complete).
    storage : {"raw", "fibers"}
        How the recording keeps its frames (:mod:`optitac_edge.io.frame_store`); ``fibers`` finds the
        fibers in the rest frames with :func:`~optitac_edge.calibration.fibers.calibrate_fibers`.
    name : str
        One of :data:`SCENARIOS`.
    seed : int
        Positions, sizes, angles, frame noise and per-press depth jitter (default 0).
    frames : int or None
        Length of ``rest`` / ``demo`` / ``drift``; truncation of the others (see
        :func:`schedule`).
    optics : CameraOptics
        The simulated camera (default ``CameraOptics()``); a ``variant``'s
        overrides (geometry, lens, illumination, noise) replace its fields,
        keeping width, height, rgb and dark_fibers.
    skin : SkinModel or None
        The skin; None (default): the variant's, drawn around the ``physics``' skin.
    layout : FiberLayout or None
        Fiber layout (default hex_layout()).
    sensor_seed : int or None
        The physical sensor's randomness; None (default):
        :func:`~optitac_edge.sim.drift.variant_sensor_seed` (:data:`SENSOR_SEED`
        for variant 0, the same sensor for every scenario and seed).
    day : int
        Recording session: ``SessionDrift.for_day(day, sensor_seed)`` (default 0:
        nominal, no drift). Ignored if ``drift`` is given.
    variant : int
        Simulated sensor, see :func:`~optitac_edge.sim.drift.sensor_variant`
        (default 0: the default sensor).
    physics : str
        The simulated physics (:data:`~optitac_edge.sim.physics.PHYSICS`, default ``default``): the skin
        the variant's is drawn around, and how much the ``day`` drifts.
    drift : SessionDrift or None
        Explicit session drift instead of ``day``.
    warmup : float
        ``drift`` scenario only: relative LED brightness change from the first
        to the last frame (default :data:`DRIFT_WARMUP` = +0.03; -0.03 dims,
        the harder case for baseline tracking: it looks like a faint press).
    patch : PatchPlacement or None
        The sensor is one patch of a camera reading several
        (:class:`~optitac_edge.sim.patches.PatchFrames`): the scenario is
        rendered at the patch's region size and pasted into whole camera
        frames where the other patches rest. ``optics`` then sets only ``rgb``
        (the size is the region's) and the sensor is the patch's.

    Returns
    -------
    Path
        ``out_dir``. ``meta.json`` holds ``rest_frames``, ``fps`` and a
        ``simulator`` object: scenario, seed, sensor_seed, day, variant, physics, optics,
        skin, drift, scale_px_per_mm, centre_px, rest_peak_gray (nominal),
        ``fiber_centres_px`` (N x [col, row], layout order, including the day's
        camera shift: the ground truth of the fiber map) and ``real_depth_mm``
        ([first frame, real depth] of every press; ``truth.csv`` has the
        commanded depth).
    """
    world = physics_named(physics)
    if layout is None:
        layout = hex_layout(*world.array) if world.array is not None else hex_layout()
    if patch is not None:
        region = patch.region
        optics = replace(optics, width=region.width, height=region.height)
        sensor_seed = patch.frames.sensors[patch.index].sensor_seed
    overrides, variant_skin = sensor_variant(variant, optics.width, optics.height, layout, world.skin)
    optics = optics_for(layout, replace(optics, **overrides) if overrides else optics)
    if world.optics:  # the physics' own camera, for its own array
        optics = replace(optics, **{k: v for k, v in world.optics.items() if k not in ("width", "height")})
    skin = skin_for(layout, variant_skin) if skin is None else skin
    sensor_seed = variant_sensor_seed(variant) if sensor_seed is None else sensor_seed
    moving = name in MOTION_SCENARIOS
    fps = MOTION_FPS if moving else FPS
    shots, tares = snapshot_session(layout, seed, frames=frames) if name in SNAPSHOT_SCENARIOS else ([], [])
    plan: list[Frame] | list[MotionFrame] = (motion_schedule(name, seed, frames, layout) if moving
                                             else [s.press for s in shots] if shots
                                             else schedule(name, seed, frames, layout, skin))
    if drift is None:
        drift = SessionDrift.for_day(day, sensor_seed, scale=world.day_drift)
    drift = scenario_drift(name, drift, len(plan), warmup, fps)
    sensor = SimulatedSensor(
        layout, optics, skin, seed=seed, sensor_seed=sensor_seed, drift=drift, fps=fps,
        wander=None if world.wander is None else WanderingLight(layout, world.wander, sensor_seed, day, seed),
        colours=FiberColours.draw(layout.n_fibers, sensor_seed) if world.colour_coded and optics.rgb else None,
    )
    simulator = _simulator_meta(sensor, patch, scenario=name, seed=seed, sensor_seed=sensor_seed, day=day,
                                variant=variant, physics=physics, optics=optics.to_dict(), skin=skin.to_dict(),
                                drift=drift.to_dict())
    frame_shape = sensor.frame_shape if patch is None else patch.frames.frame_shape
    extra: dict[str, object] = {"simulator": simulator, LAYOUT_KEY: layout_meta(sensor.layout)}
    if tares:
        extra["tares"] = tares
    meta = RecordingMeta(rest_frames=MOTION_REST_FRAMES if moving else LEAD_FRAMES if shots else REST_FRAMES,
                         fps=1.0 if shots else fps, extra=extra)
    out = Path(out_dir)
    log.info("simulating %s (seed %d, day %d, variant %d, %s physics): %d frames of %s into %s",
             name, seed, day, variant, physics, len(plan), frame_shape, out)
    load_cell = name in ("depths", "snapshots")
    with RecordingWriter(out, len(plan), frame_shape, meta, with_truth=True,
                         force_column=load_cell, replace=fresh, storage=storage, motion_columns=moving,
                         find_fibers=_find_fibers(layout, optics) if storage == "fibers" else None) as writer:
        if moving:
            simulator["real_depth_mm"] = _render_motion(writer, sensor, plan, patch, seed)  # type: ignore[arg-type]
        elif shots:
            simulator["real_depth_mm"] = _render_snapshots(writer, sensor, shots, clamp_radius_mm(layout.xy_mm, skin))
        else:
            simulator["real_depth_mm"] = _render(writer, sensor, plan, patch,  # type: ignore[arg-type]
                                                 clamp_radius_mm(layout.xy_mm, skin) if load_cell else None)
    return out


def _render_snapshots(writer: RecordingWriter, sensor: SimulatedSensor, shots: list[Snapshot],
                      clamp_r: float) -> list[list[float]]:
    """Every snapshot at its own time, its truth row where it is scored (a press with its load cell's force);
    ``[frame, real depth]`` of each press."""
    real_depths: list[list[float]] = []
    for i, shot in enumerate(shots):
        dark = sensor.darkening(() if shot.press is None else (shot.press,))
        force = math.nan
        if shot.press is not None:
            real = sensor.last_real_indenters[0]
            real_depths.append([i, round(real.depth_mm, 5)])
            force = contact_force_n(real, clamp_r, sensor.skin)
        writer.write(i, sensor.frame_from_darkening(dark, t_s=shot.t_s), round(shot.t_s * 1e9))
        if shot.scored:
            writer.write_truth(i, shot.press, force_n=force)
        sensor.darkening(())  # the next snapshot is a press of its own
    return real_depths


def _render_motion(writer: RecordingWriter, sensor: SimulatedSensor, plan: list[MotionFrame],
                   patch: PatchPlacement | None, seed: int) -> list[list[float]]:
    """Every frame of a motion scenario and its truth row (with the motion columns) into ``writer``;
    ``[first frame, real depth]`` of each press (its depth when fully pressed)."""
    factors = press_depth_factors(plan, sensor.drift.depth_jitter, seed)
    real_depths: list[list[float]] = []
    last: Indenter | None = None
    dark = sensor.darkening(())
    fps = sensor.fps
    for i, f in enumerate(plan):
        real = real_indenter(f, factors)
        if real != last:
            dark = sensor.darkening(()) if real is None else sensor.press_darkening((real,))
            last = real
        if f.press >= 0 and (i == 0 or plan[i - 1].press != f.press):
            real_depths.append([i, round(MOTION_DEPTH_MM * factors[f.press], 5)])
        frame = sensor.frame_from_darkening(dark, t_s=i / fps)
        if patch is not None:
            frame = patch.paste(frame)
        writer.write(i, frame, round(i * 1e9 / fps))
        writer.write_truth(i, f.indenter, motion=(f.vx_mm_s, f.vy_mm_s, f.motion))
    return real_depths


def _simulator_meta(sensor: SimulatedSensor, patch: PatchPlacement | None, **given: object) -> dict[str, object]:
    """The recording's ``simulator`` object: what made it (``given``) and the sensor's ground truth, in whole
    camera frame pixels for a patch."""
    proj = sensor.renderer.projection
    simulator: dict[str, object] = {
        **given,
        "scale_px_per_mm": proj.scale,
        "centre_px": [proj.cx, proj.cy],
        "rest_peak_gray": np.round(sensor.rest_peak, 3).tolist(),
        "fiber_centres_px": np.round(sensor.fiber_centres_px, 4).tolist(),
    }
    if patch is not None:  # the ground truth in whole-frame pixels
        offset = np.array([patch.region.x, patch.region.y])
        simulator["centre_px"] = [proj.cx + patch.region.x, proj.cy + patch.region.y]
        simulator["fiber_centres_px"] = np.round(sensor.fiber_centres_px + offset, 4).tolist()
        simulator["region"] = patch.region.to_dict()
    return simulator


def _render(writer: RecordingWriter, sensor: SimulatedSensor, plan: list[Frame], patch: PatchPlacement | None,
            clamp_r: float | None) -> list[list[float]]:
    """Every frame of ``plan`` and its truth row into ``writer``; ``[first frame, real depth]`` of each press.

    ``clamp_r`` (mm): the load cell's clamp radius, for the force column (None: no load cell).
    """
    real_depths: list[list[float]] = []
    force = math.nan
    last: Frame = None
    dark = sensor.darkening(())
    for i, press in enumerate(plan):
        if press is not last:
            dark = sensor.darkening(() if press is None else (press,))
            if press is not None:
                real = sensor.last_real_indenters[0].depth_mm
                real_depths.append([i, round(real, 5)])
                if clamp_r is not None:
                    force = contact_force_n(sensor.last_real_indenters[0], clamp_r, sensor.skin)
            last = press
        frame = sensor.frame_from_darkening(dark, t_s=i / FPS)
        if patch is not None:
            frame = patch.paste(frame)
        writer.write(i, frame, round(i * 1e9 / FPS))
        writer.write_truth(i, press, force_n=math.nan if press is None else force)
    return real_depths
