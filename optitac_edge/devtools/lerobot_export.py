"""Recordings as a LeRobot dataset (``optitac-edge export-lerobot``), written by LeRobot's own writer.

Each recording is one episode, replayed through the pipeline with the bundle as ``optitac-edge replay`` does (its
own baseline from its rest frames, its tares); every frame's tactile features
(:mod:`optitac_edge.devtools.lerobot_features`) and, where the recordings have one, their truth. The dataset
is written beside its destination and renamed into place when complete: an interrupted export leaves nothing
at the destination, and an existing destination is never written over.

LeRobot's writer is the ``lerobot-dataset`` package (its module ``ledataset``), which imports torch and
torchvision: ``pip install 'optitac-edge[lerobot]'``, best in an environment of its own (docs/lerobot.md).
"""

from __future__ import annotations

import logging
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from optitac_edge.devtools import lerobot_features as lf
from optitac_edge.errors import OptiTacError, OutputError
from optitac_edge.io.files import sole_writer

if TYPE_CHECKING:
    from optitac_edge.io.recording import Recording

log = logging.getLogger(__name__)

#: The extra that brings LeRobot's writer, named in the line a missing one gives.
EXTRA = "pip install 'optitac-edge[lerobot]' (it brings torch: best in an environment of its own, docs/lerobot.md)"


@dataclass(frozen=True)
class ExportJob:
    """What to export.

    Attributes
    ----------
    recordings : tuple of Path
        One episode each, in this order; all of one frame rate, one sensor's frames.
    bundle : Path
        The calibration bundle the frames are replayed with.
    output : Path
        The dataset's directory (must not exist).
    repo_id : str
        The dataset's name (``owner/name``), as LeRobot's loader is given it.
    task : str
        The task of every frame (LeRobot's ``task``).
    video : bool
        Add the tactile surface as a 224 × 224 video.
    """

    recordings: tuple[Path, ...]
    bundle: Path
    output: Path
    repo_id: str = "optitac/tactile"
    task: str = "touch"
    video: bool = False


@dataclass(frozen=True)
class ExportReport:
    """What an export wrote: episodes, frames, bytes on disk and seconds taken."""

    episodes: int
    frames: int
    bytes: int
    seconds: float


def whole_fps(recs: Sequence[Recording]) -> int:
    """The recordings' one frame rate as a whole number (LeRobot's ``fps`` is an int), or one line."""
    rates = {float(r.meta.fps) for r in recs}
    if len(rates) != 1:
        raise OptiTacError(f"one dataset has one frame rate; these recordings have {sorted(rates)} fps")
    fps = rates.pop()
    if abs(fps - round(fps)) > 1e-6 or round(fps) < 1:
        raise OptiTacError(f"a LeRobot dataset's frame rate is a whole number; the recordings' is {fps:g} fps")
    return round(fps)


def _load_writer() -> Any:  # LeRobot's LeRobotDataset class (the library has no types)
    try:
        from ledataset.datasets.lerobot_dataset import LeRobotDataset
    except ImportError as exc:
        raise OptiTacError(f"export-lerobot needs LeRobot's dataset writer ({exc.name or exc} is missing): "
                           f"{EXTRA}") from None
    return LeRobotDataset


def export_lerobot(job: ExportJob, progress: bool | None = None) -> ExportReport:
    """Write ``job``'s recordings as a LeRobot dataset at ``job.output``.

    Raises
    ------
    OptiTacError
        LeRobot's writer missing, recordings of several rates or sensors, frames not of the bundle, an existing
        output, another export writing it: one line naming it.
    """
    if not job.output.parent.is_dir():
        raise OutputError(f"{job.output.parent}: no such directory")
    with sole_writer(job.output):  # one export per destination: a second is refused in one line
        if job.output.exists() or job.output.is_symlink():
            raise OutputError(f"{job.output}: exists; a dataset is written to a new directory, never over one")
        return _export(job, progress)


def _export(job: ExportJob, progress: bool | None) -> ExportReport:
    """:func:`export_lerobot`'s work, its destination locked."""
    from optitac_edge.calibration.measure import replay_recording
    from optitac_edge.core.pipeline import Pipeline
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.recording import Recording

    writer = _load_writer()
    t0 = time.monotonic()
    bundle = load_bundle(job.bundle)
    recs = [Recording(p) for p in job.recordings]
    fps = whole_fps(recs)
    truths = [r.truth for r in recs]
    shapes = None if all(t is None for t in truths) else \
        lf.shape_names([str(s) for t in truths if t is not None for s in t.shape])
    features = lf.tactile_features(bundle.layout.ids, video=job.video, truth_shapes=shapes)
    # a directory of this export's own (never a name a user's folder may have), the dataset written inside it
    work = Path(tempfile.mkdtemp(prefix=f".{job.output.name}.", suffix=".partial", dir=job.output.parent))
    partial = work / "dataset"
    frames = 0
    try:
        dataset = writer.create(job.repo_id, fps, features, root=partial, robot_type="optitac",
                                use_videos=job.video)
        show = sys.stderr.isatty() if progress is None else progress
        for episode, (path, rec) in enumerate(zip(job.recordings, recs)):
            pipeline = Pipeline(bundle, fps=rec.meta.fps)
            rows = {} if rec.truth is None else lf.truth_rows(rec.truth)
            for i, result in replay_recording(rec, pipeline, progress=show, desc=path.name):
                row: dict[str, object] = {**lf.frame_values(result, pipeline.signal), "task": job.task}
                if shapes is not None:
                    row.update(lf.truth_values(rec.truth, rows.get(i), shapes))
                if job.video:
                    row[lf.IMAGE] = lf.surface_image(pipeline.surface_levels())
                dataset.add_frame(row)
            dataset.save_episode()
            frames += len(rec)
            log.info("episode %d: %s, %d frames", episode, path, len(rec))
        dataset.finalize()
        partial.rename(job.output)
    finally:
        shutil.rmtree(work, ignore_errors=True)  # what this export made, and nothing else
    size = sum(f.stat().st_size for f in job.output.rglob("*") if f.is_file())
    return ExportReport(len(recs), frames, size, time.monotonic() - t0)

