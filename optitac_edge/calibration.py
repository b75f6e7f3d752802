"""Fiber calibration: rest frames in, a complete calibration bundle out."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from .bundle import CalibrationBundle, ContactThresholds
from .errors import FiberMapError
from .frames import frame_geometry, to_gray
from .grid import SurfaceGrid
from .layout import FiberLayout, hex_layout

log = logging.getLogger(__name__)


def _jsonable(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        obj = dataclasses.asdict(obj)
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def calibrate_fibers(
    rest_frames: Sequence[np.ndarray] | np.ndarray,
    pixel_format: str,
    layout: FiberLayout | None = None,
    rotation_hint_deg: float = 0.0,
    mirror: bool = False,
    thresholds: ContactThresholds | None = None,
) -> CalibrationBundle:
    """Build a calibration bundle from contact-free frames.

    Parameters
    ----------
    rest_frames : sequence of ndarray, uint8
        At least one contact-free frame in ``pixel_format``; all the same size.
    pixel_format : str
        ``gray``, ``rgb`` or ``yuv420``.
    layout : FiberLayout, optional
        The sensor's CAD layout; the default 217-fiber hexagonal layout if None.
    rotation_hint_deg, mirror
        Orientation hint (see docs/formats.md); the hint must be within 20 degrees.
    thresholds : ContactThresholds, optional
        Contact thresholds to store.

    Raises
    ------
    FiberMapError
        If the fibers cannot be found reliably.
    """
    from .fiber_map import build_fiber_map
    from .surface import build_interpolation_matrix

    layout = hex_layout() if layout is None else layout
    if len(rest_frames) == 0:
        raise FiberMapError("no rest frames to calibrate from")
    h, w = frame_geometry(rest_frames[0].shape, pixel_format)
    gray = np.stack([to_gray(np.asarray(f), pixel_format) for f in rest_frames])
    result = build_fiber_map(gray, layout, rotation_hint_deg=rotation_hint_deg, mirror=mirror,
                             pixel_format=pixel_format)
    grid = SurfaceGrid.over_layout(layout)
    matrix = build_interpolation_matrix(layout, grid)
    report = _jsonable(result.report)
    log.info("fiber calibration of %dx%d %s frames: %s", w, h, pixel_format, report)
    return CalibrationBundle(
        layout=layout, transform=result.transform, fibers=result.table, grid=grid,
        interpolation=matrix, thresholds=thresholds or ContactThresholds(),
        fiber_map_report=report,
    )
