"""A sensor's region of a camera frame, and the region a calibration bundle was placed in.

Several sensors can share one camera (:mod:`optitac_edge.calibration.region`
places each sensor's bundle in the whole frame); the service checks that each
bundle was placed in the region its board config gives the sensor.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.errors import BundleError

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


def describe_region(region: Region | None) -> str:
    """``region [x, y, width, height]``, or ``the whole frame``."""
    if region is None:
        return "the whole frame"
    return f"region [{region.x}, {region.y}, {region.width}, {region.height}]"


def check_region(bundle: CalibrationBundle, region: Region | None, where: str, sensor_id: int) -> CalibrationBundle:
    """``bundle``, when it was placed in ``region`` (None: the whole frame).

    Parameters
    ----------
    where : str
        What the error line starts with (the file and the sensor).
    sensor_id : int
        The board's id of the sensor (the error says to calibrate it with ``--sensor ID``).

    Raises
    ------
    BundleError
        One line: the bundle's region is not valid, or not the board's.
    """
    try:
        got = bundle_region(bundle)
    except (TypeError, ValueError) as exc:
        raise BundleError(f"{where}: the bundle's region is not valid ({exc})") from None
    if got != region:
        raise BundleError(f"{where}: the bundle was built for {describe_region(got)}, the board puts the sensor in "
                          f"{describe_region(region)} (calibrate it with --sensor {sensor_id})")
    return bundle
