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

from dataclasses import dataclass, replace
from typing import Any

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.fiber_table import FiberTable

#: ``CalibrationBundle.extra_meta`` key of the region a bundle was placed in.
REGION_KEY = "region"


@dataclass(frozen=True)
class Region:
    """A rectangle of a camera frame, px: columns ``x … x + width - 1``, rows ``y … y + height - 1``."""

    x: int
    y: int
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("x", "y", "width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int):
                raise TypeError(f"region {name} must be an integer, got {v!r}")
        if self.x < 0 or self.y < 0 or self.width < 1 or self.height < 1:
            raise ValueError(f"region {self.to_dict()} needs x, y >= 0 and a size of at least 1 px")

    def inside(self, frame_width: int, frame_height: int) -> bool:
        """The region lies within a frame of this size."""
        return self.x + self.width <= frame_width and self.y + self.height <= frame_height

    def overlaps(self, other: Region) -> bool:
        return (self.x < other.x + other.width and other.x < self.x + self.width
                and self.y < other.y + other.height and other.y < self.y + self.height)

    def to_dict(self) -> dict[str, int]:
        return {"x": self.x, "y": self.y, "width": self.width, "height": self.height}

    @classmethod
    def from_dict(cls, d: Any) -> Region:
        if not isinstance(d, dict) or set(d) != {"x", "y", "width", "height"}:
            raise ValueError(f"a region is {{x, y, width, height}}, got {d!r}")
        return cls(d["x"], d["y"], d["width"], d["height"])


def bundle_region(bundle: CalibrationBundle) -> Region | None:
    """The region a bundle was placed in (None: it covers its whole frame)."""
    d = bundle.extra_meta.get(REGION_KEY)
    return None if d is None else Region.from_dict(d)


def place_fiber_table(table: FiberTable, region: Region, frame_width: int, frame_height: int) -> FiberTable:
    """``table`` (built on a crop of ``region``'s size) with its pixels in the whole frame."""
    if (table.width, table.height) != (region.width, region.height):
        raise ValueError(f"the fiber table is for {table.width}x{table.height} frames, the region is "
                         f"{region.width}x{region.height}")
    if not region.inside(frame_width, frame_height):
        raise ValueError(f"region {region.to_dict()} leaves the {frame_width}x{frame_height} frame")
    row, col = table.pixel_index // table.width + region.y, table.pixel_index % table.width + region.x
    offset = [region.x, region.y]
    return FiberTable(height=frame_height, width=frame_width, pixel_format=table.pixel_format,
                      pixel_index=(row * frame_width + col).astype(table.pixel_index.dtype),
                      pixel_start=table.pixel_start, centroid_px=table.centroid_px + offset, dead=table.dead,
                      unmatched_px=table.unmatched_px + offset)


def place_bundle(bundle: CalibrationBundle, region: Region, frame_width: int, frame_height: int) -> CalibrationBundle:
    """A bundle calibrated on ``region``'s crop, placed in the whole ``frame_width`` x ``frame_height`` frame.

    Raises
    ------
    ValueError
        If the bundle is not for frames of the region's size, already placed, or the region leaves the frame.
    """
    if REGION_KEY in bundle.extra_meta:
        raise ValueError(f"the bundle is already placed in region {bundle.extra_meta[REGION_KEY]}")
    fibers = place_fiber_table(bundle.fibers, region, frame_width, frame_height)
    transform = replace(bundle.transform, cx=bundle.transform.cx + region.x, cy=bundle.transform.cy + region.y)
    return bundle.with_updates(fibers=fibers, transform=transform,
                               extra_meta={**bundle.extra_meta, REGION_KEY: region.to_dict()})
