"""A calibration from files to a saved bundle, in one call a step: what ``optitac-edge calibrate`` runs.

The command line turns its arguments into a job (which recordings, which bundle, the board's region and
check); the job reads the recordings, calibrates, and saves the bundle atomically
(:func:`~optitac_edge.io.bundle_file.save_bundle`), and says what it did in an outcome the command line
prints. Nothing here prints or reads arguments.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.region import Region
from optitac_edge.errors import OptiTacError

if TYPE_CHECKING:
    from optitac_edge.calibration.orientation import OrientationFit

#: The steps that update a bundle (``calibrate fibers`` makes one: :class:`FiberMapJob`).
STEPS = ("orientation", "levels", "centroid", "width", "shapes", "depth")


@dataclass(frozen=True)
class FiberMapJob:
    """``calibrate fibers``: the fiber map of a recording's rest frames, saved at ``output``.

    Attributes
    ----------
    recording, output : Path
    region : Region or None
        Where the board puts the sensor in the frame (None: the whole frame).
    camera : tuple of (str, int, int), optional
        What the board's camera delivers, ``(who, width, height)``: the recording's frames must be that size.
    layout : Path or None
        A layout CSV (None: the hexagonal default).
    rotation_deg, mirror
        The orientation hint; with neither given, a bundle at ``output`` whose orientation presses settled
        gives it (and the new map keeps that orientation when it is turned as the old one was).
    """

    recording: Path
    output: Path
    region: Region | None = None
    camera: tuple[str, int, int] | None = None
    layout: Path | None = None
    rotation_deg: float | None = None
    mirror: bool = False


@dataclass(frozen=True, eq=False)
class FiberMapOutcome:
    """What :func:`map_fibers` saved: the bundle, and whether an earlier settled orientation was kept
    (``kept``) or lost (``lost``: the new map is turned otherwise; settle it again)."""

    bundle: CalibrationBundle
    kept: bool = False
    lost: bool = False


def map_fibers(job: FiberMapJob) -> FiberMapOutcome:
    """Run :class:`FiberMapJob`: read the rest frames, map the fibers, save the bundle."""
    from optitac_edge.calibration.orientation import keep_orientation, settles
    from optitac_edge.calibration.sensor import calibrate_sensor
    from optitac_edge.core.layout import hex_layout
    from optitac_edge.io.bundle_file import readable_bundle, save_bundle
    from optitac_edge.io.layout_csv import load_layout_csv
    from optitac_edge.io.recording import Recording

    rec = Recording(job.recording)
    if job.region is not None and job.camera is not None and (rec.width, rec.height) != job.camera[1:]:
        who, width, height = job.camera
        raise OptiTacError(f"{job.recording}: frames are {rec.width}x{rec.height}, {who} delivers {width}x{height}")
    # the layout given, else the one the recording was made with (a sensor of a board's region: the board's)
    layout = (load_layout_csv(job.layout) if job.layout is not None
              else rec.layout if job.region is None else None)
    hinted = job.rotation_deg is not None or job.mirror
    previous = None if hinted else readable_bundle(job.output)
    settled = previous if previous is not None and settles(previous, layout or hex_layout()) else None
    rotation, mirror = ((job.rotation_deg or 0.0, job.mirror) if settled is None
                        else (settled.transform.rotation_deg, settled.transform.mirror))
    bundle = calibrate_sensor(rec.rest_frames(), rec.pixel_format, job.region, layout=layout,
                              rotation_hint_deg=rotation, mirror=mirror, times_ns=rec.t_ns[: rec.meta.rest_frames])
    kept = None if settled is None else keep_orientation(settled, bundle)
    saved = save_bundle(bundle if kept is None else kept, job.output)
    return FiberMapOutcome(saved, kept=kept is not None, lost=settled is not None and kept is None)


@dataclass(frozen=True)
class StepJob:
    """A step of :data:`STEPS` on recordings with truth, updating the bundle at ``bundle`` in place.

    Attributes
    ----------
    step : str
    recordings : tuple of Path
        Days or sessions, each with its own baseline.
    bundle : Path
    check : callable, optional
        ``check(bundle, path)`` raises when the bundle read is not the one the board expects there (its region).
    seed : int
        shapes: the seed of the held-out split and the fits.
    width_model : str
        width: the per-axis form (:func:`~optitac_edge.calibration.steps.calibrate_width`'s ``kind``).
    fill, contacts : str
        centroid: :func:`~optitac_edge.calibration.steps.calibrate_centroid`'s.
    """

    step: str
    recordings: tuple[Path, ...]
    bundle: Path
    check: Callable[[CalibrationBundle, Path], object] | None = None
    seed: int = 0
    width_model: str = "auto"
    fill: str = "auto"
    contacts: str = "auto"

    def __post_init__(self) -> None:
        if self.step not in STEPS:
            raise ValueError(f"unknown calibration step {self.step!r} (one of {', '.join(STEPS)})")


@dataclass(frozen=True, eq=False)
class StepOutcome:
    """What :func:`run_step` saved: the bundle, the step's summary, and the orientation step's fit."""

    bundle: CalibrationBundle
    summary: dict[str, Any]
    fit: OrientationFit | None = None


def run_step(job: StepJob) -> StepOutcome:
    """Run :class:`StepJob`: read the bundle and the recordings, fit the step's model, save the bundle."""
    from optitac_edge.calibration import steps
    from optitac_edge.io.bundle_file import load_bundle, save_bundle
    from optitac_edge.io.recording import Recording, refuse_repeated

    recs = [Recording(path) for path in job.recordings]
    refuse_repeated(recs)
    bundle = load_bundle(job.bundle)
    if job.check is not None:
        job.check(bundle, job.bundle)
    fit: OrientationFit | None = None
    summary: dict[str, Any] = {}
    if job.step == "orientation":
        bundle, fit = steps.calibrate_orientation(recs, bundle)
    elif job.step == "levels":
        bundle, summary = steps.calibrate_levels(recs, bundle)
    elif job.step == "centroid":
        bundle, summary = steps.calibrate_centroid(recs, bundle, fill=job.fill, bundle_path=str(job.bundle),
                                                   contacts=job.contacts)
    elif job.step == "width":
        bundle, summary = steps.calibrate_width(recs, bundle, kind=job.width_model)
    elif job.step == "shapes":
        bundle, summary = steps.calibrate_shapes(recs, bundle, seed=job.seed)
    else:
        bundle, summary = steps.calibrate_depth(recs, bundle)
    return StepOutcome(save_bundle(bundle, job.bundle), summary, fit)
