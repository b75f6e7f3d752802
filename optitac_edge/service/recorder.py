"""Save frames of a board's camera as a recording (``optitac-edge record``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from optitac_edge.config import BoardConfig
from optitac_edge.errors import OptiTacError
from optitac_edge.io.recording import MIN_REST_FRAMES, RecordingMeta
from optitac_edge.io.recording_paths import check_writable_recording
from optitac_edge.io.recording_writer import RecordingWriter
from optitac_edge.service.bundles import fiber_finder
from optitac_edge.service.wiring import open_board_camera


class Recorded(NamedTuple):
    """What :func:`record_board` wrote, and the camera's pace: ``span_s`` from the first frame to the last,
    ``gaps`` (frame intervals over 1.5 periods of the camera's rate), ``missing`` (frames the gaps would have
    held) and ``dropped`` (frames the camera itself counted as dropped)."""

    frames: int
    width: int
    height: int
    pixel_format: str
    meta: RecordingMeta
    span_s: float = 0.0
    gaps: int = 0
    missing: int = 0
    dropped: int = 0


def frame_gaps(t_ns: np.ndarray, fps: float) -> tuple[int, int]:
    """(intervals longer than 1.5 frame periods, frames they would have held) of capture times ``t_ns``
    (shape (N,), ns) at ``fps``."""
    period = 1e9 / fps
    dt = np.diff(np.asarray(t_ns, dtype=np.int64)).astype(np.float64)
    late = dt > 1.5 * period
    return int(late.sum()), int(np.maximum(np.rint(dt[late] / period) - 1, 0).sum())


def record_board(config: BoardConfig, path: str | Path, frames: int, rest_frames: int,
                 mcap: bool = False, replace: bool = False, storage: str = "fibers") -> Recorded:
    """Write ``frames`` frames of the board's camera to the recording directory ``path`` (with ``mcap``:
    to the MCAP file ``path``, frames as sensor_msgs/Image, :mod:`optitac_edge.io.recording_mcap`).

    The first ``rest_frames`` must be contact-free (``meta.json`` says so). A complete recording at
    ``path`` is refused unless ``replace`` (then replaced once the new one is complete). ``storage``:
    a directory's frames as ``fibers`` (the rest frames and each fiber's light after them) or ``raw``
    (:mod:`optitac_edge.io.frame_store`); an MCAP file holds raw frames.

    Raises
    ------
    OptiTacError
        On bad counts, a YUV420 camera (recordings hold gray or RGB frames) or a
        camera that ends early.
    """
    if frames < rest_frames or rest_frames < MIN_REST_FRAMES:
        raise OptiTacError(f"--frames must be >= --rest-frames >= {MIN_REST_FRAMES}")
    if mcap:
        from optitac_edge.io.recording_mcap import McapRecordingWriter
    check_writable_recording(path, replace)  # refused before the camera opens
    with open_board_camera(config) as camera:
        if camera.pixel_format == "yuv420":
            raise OptiTacError("recordings hold gray or RGB frames: set camera.pixel_format = 'gray'")
        extra: dict[str, object] = {"board": config.source, "camera": config.camera.backend}
        layout_path = config.calibration.layout_path
        if layout_path is not None and len(config.sensors) == 1:  # the sensor's layout, for calibrate fibers
            from optitac_edge.io.layout_csv import load_layout_csv
            from optitac_edge.io.recording import LAYOUT_KEY, layout_meta

            extra[LAYOUT_KEY] = layout_meta(load_layout_csv(layout_path))
        meta = RecordingMeta(rest_frames=rest_frames, fps=camera.fps, extra=extra)
        writer: Any = (McapRecordingWriter(path, meta.to_json(), replace=replace) if mcap else
                       RecordingWriter(path, frames, camera.frame_shape, meta, replace=replace, storage=storage,
                                       find_fibers=fiber_finder(config)))
        times = np.zeros(frames, dtype=np.int64)
        with writer:
            for i in range(frames):
                captured = camera.read(config.camera.timeout_s)
                if captured is None:
                    raise OptiTacError(f"the camera ended after {i} frames")
                writer.write(i, captured.frame, captured.t_ns)
                times[i] = captured.t_ns
        dropped = int(getattr(camera, "frames_dropped", 0))
    gaps, missing = frame_gaps(times, camera.fps)
    return Recorded(frames, camera.width, camera.height, camera.pixel_format, meta,
                    (int(times[-1]) - int(times[0])) / 1e9, gaps, missing, dropped)
