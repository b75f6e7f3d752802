"""Calibration bundles of the simulated sensor, built by the library (for tests, the bench and demos).

The same steps a user runs on a real sensor (``optitac-edge sim`` then
``calibrate fibers|centroid|width|shapes``), as function calls: a rest
recording gives the fiber map, then one scenario per calibration model.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from optitac_edge.calibration import steps
from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.errors import BundleError
from optitac_edge.io.bundle_file import load_bundle, save_bundle
from optitac_edge.io.recording import Recording
from optitac_edge.sim.optics import CameraOptics
from optitac_edge.sim.scenarios import write_scenario

log = logging.getLogger(__name__)

#: Calibration models after the fiber map, in the order they are fitted: (model, scenario, seed offset).
MODEL_STEPS: tuple[tuple[str, str, int], ...] = (("centroid", "seen", 1), ("width", "widths", 2),
                                                 ("shapes", "shapes", 3))
MODELS = tuple(m for m, _, _ in MODEL_STEPS)


def build_sim_bundle(path: str | Path, *, rgb: bool = False, models: Sequence[str] = MODELS, seed: int = 2,
                     workdir: str | Path | None = None) -> Path:
    """Calibrate the built-in simulated sensor into the bundle ``path``; returns ``path``.

    Parameters
    ----------
    path : path-like
        The bundle to write (its directory is created).
    rgb : bool
        Calibrate for RGB frames instead of gray.
    models : sequence of {"centroid", "width", "shapes"}
        The calibration models to fit after the fiber map (default all).
    seed : int
        Seed of the rest recording; model ``k`` uses ``seed + k``.
    workdir : path-like, optional
        Where the recordings are written (default: next to the bundle).

    Raises
    ------
    ValueError
        On an unknown model name.
    """
    unknown = sorted(set(models) - set(MODELS))
    if unknown:
        raise ValueError(f"unknown calibration models {unknown} (known: {', '.join(MODELS)})")
    path = Path(path)
    work = Path(workdir) if workdir is not None else path.parent
    tag = "rgb" if rgb else "gray"
    optics = CameraOptics(rgb=rgb)
    # the work directory's recordings are this function's own, made again from the same seeds
    rest = write_scenario(work / f"rest-{tag}", "rest", seed=seed, optics=optics, fresh=True)
    rec = Recording(rest)
    bundle = save_bundle(calibrate_fibers(rec.rest_frames(), rec.pixel_format), path)
    for model, scenario, offset in MODEL_STEPS:
        if model not in models:
            continue
        log.info("simulated bundle: fitting the %s model", model)
        rec = Recording(write_scenario(work / f"{scenario}-{tag}", scenario, seed=seed + offset, optics=optics,
                                       fresh=True))
        if model == "centroid":
            bundle, _ = steps.calibrate_centroid(rec, bundle)
        elif model == "width":
            bundle, _ = steps.calibrate_width(rec, bundle)
        else:
            bundle, _ = steps.calibrate_shapes(rec, bundle)
        bundle = save_bundle(bundle, path)
    return path


def _usable(path: Path) -> bool:
    """A cached bundle that loads and has surface factors (else it is rebuilt)."""
    try:
        return path.exists() and load_bundle(path).surface_factors is not None
    except BundleError:
        return False


def cached_sim_bundle(workdir: str | Path, *, rgb: bool = False) -> Path:
    """A bundle of :func:`build_sim_bundle` with every model, built once in ``workdir`` and reused.

    A cached bundle that does not load, or was written by an older optitac-edge
    without surface factors, is rebuilt.
    """
    workdir = Path(workdir)
    path = workdir / ("cal-rgb.npz" if rgb else "cal-gray.npz")
    if _usable(path):
        return path
    return build_sim_bundle(path, rgb=rgb, workdir=workdir)


#: Rest frames the fiber map of :func:`cached_layout_bundle` is calibrated from.
LAYOUT_REST_FRAMES = 30


def cached_layout_bundle(workdir: str | Path, rings: int, *, rgb: bool = False) -> Path:
    """A fiber-map-only bundle of a simulated sensor with a hexagonal array of ``rings`` rings.

    The array fills the 640 x 480 frame as the 217-fiber one does (8 rings:
    217 fibers; 12: 469; 18: 1027), so the bench compares fiber counts at
    the same frame size. Built once into ``workdir`` and reused.
    """
    import numpy as np

    from optitac_edge.core.layout import hex_layout
    from optitac_edge.sim.sensor import SimulatedSensor

    workdir = Path(workdir)
    path = workdir / f"cal-hex{rings}-{'rgb' if rgb else 'gray'}.npz"
    if _usable(path):
        return path
    layout = hex_layout(rings)
    sensor = SimulatedSensor(layout=layout, optics=CameraOptics(rgb=rgb), seed=1)
    frames = np.stack([sensor.frame(()) for _ in range(LAYOUT_REST_FRAMES)])
    workdir.mkdir(parents=True, exist_ok=True)
    save_bundle(calibrate_fibers(frames, "rgb" if rgb else "gray", layout=layout), path)
    return path
