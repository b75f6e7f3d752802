"""``optitac-edge orient``: the guided orientation procedure on a live camera."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from optitac_edge.calibration.edge_presses import EdgePresses
from optitac_edge.calibration.orientation import OrientationFit
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.frame_engine import Skip
from optitac_edge.core.pipeline import Pipeline
from optitac_edge.errors import CameraError, OrientationError
from optitac_edge.io.cameras.base import Camera

log = logging.getLogger(__name__)


def orient_live(camera: Camera, bundle: CalibrationBundle, timeout_s: float,
                on_prompt: Callable[[str], None], stop: threading.Event | None = None,
                read_timeout_s: float = 2.0) -> OrientationFit:
    """Run :class:`~optitac_edge.calibration.edge_presses.EdgePresses` on ``camera`` through ``bundle``.

    ``on_prompt`` is called with each new prompt. The time limit is counted in
    the camera's frame times (after the baseline), so it is the same on any machine.

    Raises
    ------
    OrientationError
        If the presses did not decide the orientation, or ``timeout_s`` passed first.
    CameraError
        If the camera ends.
    """
    pipeline = Pipeline(bundle, fps=camera.fps)
    procedure = EdgePresses(bundle.layout)
    shown = ""
    start_ns: int | None = None
    while not procedure.done:
        if stop is not None and stop.is_set():
            raise KeyboardInterrupt
        captured = camera.read(read_timeout_s)
        if captured is None:
            raise CameraError("the camera ended before the orientation was found")
        result = pipeline.process(captured.frame, captured.t_ns)
        if result is Skip.BAD:  # says which frames the bundle wants
            bundle.fibers.check_frame(captured.frame, camera.pixel_format)
        if isinstance(result, Skip):  # dark, saturated: no press to read
            continue
        est = result.primary
        if not result.baseline_ready:
            continue
        if start_ns is None:
            start_ns = captured.t_ns
        elif captured.t_ns - start_ns > timeout_s * 1e9:
            raise OrientationError(f"no orientation within {timeout_s:g} s (last step: {procedure.prompt})")
        procedure.feed(bool(est.contact), est.x_mm, est.y_mm, captured.t_ns)
        if procedure.prompt != shown:
            shown = procedure.prompt
            on_prompt(shown)
    assert procedure.fit is not None
    if procedure.fit.symmetry is None:
        raise OrientationError(f"the two presses did not decide the orientation: {procedure.fit.reason}")
    return procedure.fit
