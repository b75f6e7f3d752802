"""Several sensors in one camera frame: a sensor's region of the frame, and its bundle placed in it.

One camera can read several fiber patches (both fingers of a gripper, fingertips
and palm). Each patch is a sensor with its own bundle, calibrated on its
region of the frame (a crop), then placed in the whole frame: its fiber table's
pixel indices, centres and image transform move by the region's offset, and the
bundle records the region. Every sensor's pipeline then takes the camera's
frame as it comes (no crop, no copy) and gathers only its own fibers' pixels,
so the cost per frame grows with the number of fibers, not with the frame size.
Done once, offline (after ``calibrate_fibers`` on the crop); nothing here runs per frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.fiber_table import FiberTable
from optitac_edge.core.frames import frame_geometry, to_gray
from optitac_edge.core.region import REGION_KEY, Region, bundle_region

__all__ = ["REGION_KEY", "Region", "bundle_region", "calibrate_region", "crop_frames", "place_bundle",
           "place_fiber_table"]


def place_fiber_table(table: FiberTable, region: Region, frame_width: int, frame_height: int,
                      pixel_format: str | None = None) -> FiberTable:
    """``table`` (built on a crop of ``region``'s size) with its pixels in the whole frame.

    ``pixel_format`` (default: the table's) is the whole frame's: a ``yuv420`` camera's crop is
    calibrated on its luma as ``gray``, and the luma plane's pixel indices are the frame's.
    """
    if (table.width, table.height) != (region.width, region.height):
        raise ValueError(f"the fiber table is for {table.width}x{table.height} frames, the region is "
                         f"{region.width}x{region.height}")
    if not region.inside(frame_width, frame_height):
        raise ValueError(f"region {region.to_dict()} leaves the {frame_width}x{frame_height} frame")
    row, col = table.pixel_index // table.width + region.y, table.pixel_index % table.width + region.x
    offset = [region.x, region.y]
    return FiberTable(height=frame_height, width=frame_width, pixel_format=pixel_format or table.pixel_format,
                      pixel_index=(row * frame_width + col).astype(table.pixel_index.dtype),
                      pixel_start=table.pixel_start, centroid_px=table.centroid_px + offset, dead=table.dead,
                      unmatched_px=table.unmatched_px + offset)


def place_bundle(bundle: CalibrationBundle, region: Region, frame_width: int, frame_height: int,
                 pixel_format: str | None = None) -> CalibrationBundle:
    """A bundle calibrated on ``region``'s crop, placed in the whole ``frame_width`` x ``frame_height`` frame.

    Raises
    ------
    ValueError
        If the bundle is not for frames of the region's size, already placed, or the region leaves the frame.
    """
    if REGION_KEY in bundle.extra_meta:
        raise ValueError(f"the bundle is already placed in region {bundle.extra_meta[REGION_KEY]}")
    fibers = place_fiber_table(bundle.fibers, region, frame_width, frame_height, pixel_format)
    transform = replace(bundle.transform, cx=bundle.transform.cx + region.x, cy=bundle.transform.cy + region.y)
    return bundle.with_updates(fibers=fibers, transform=transform,
                               extra_meta={**bundle.extra_meta, REGION_KEY: region.to_dict()})


def crop_frames(frames: Sequence[np.ndarray] | np.ndarray, pixel_format: str,
                region: Region) -> tuple[np.ndarray, str]:
    """Whole camera frames cut to ``region``: (frames (F, h, w[, 3]) C-contiguous, their pixel format).

    A ``yuv420`` frame's crop is its luma (``gray``): what the pipeline reads of it.

    Raises
    ------
    ValueError
        If the region leaves the frames.
    """
    gray_like = pixel_format == "yuv420"
    out = []
    for f in frames:
        f = to_gray(np.asarray(f), pixel_format) if gray_like else np.asarray(f)
        if not region.inside(f.shape[1], f.shape[0]):
            raise ValueError(f"region {region.to_dict()} leaves the {f.shape[1]}x{f.shape[0]} frame")
        out.append(f[region.y:region.y + region.height, region.x:region.x + region.width])
    return np.ascontiguousarray(np.stack(out)), "gray" if gray_like else pixel_format


def calibrate_region(frames: Sequence[np.ndarray] | np.ndarray, pixel_format: str, region: Region,
                     **kwargs: Any) -> CalibrationBundle:
    """The fiber map of the sensor in ``region`` of whole rest frames, placed in the frame.

    ``kwargs`` go to :func:`~optitac_edge.calibration.fibers.calibrate_fibers`
    (layout, orientation hint, ...).
    """
    from optitac_edge.calibration.fibers import calibrate_fibers

    height, width = frame_geometry(np.asarray(frames[0]).shape, pixel_format)
    cropped, crop_format = crop_frames(frames, pixel_format, region)
    bundle = calibrate_fibers(cropped, crop_format, **kwargs)
    return place_bundle(bundle, region, width, height, pixel_format)
