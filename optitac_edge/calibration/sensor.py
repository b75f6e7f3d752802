"""Calibrate one sensor where its board puts it, and check that a bundle was made for that place.

Both the command line (``calibrate fibers --sensor ID``, ``calibrate STEP --sensor ID``) and the service
(a missing bundle calibrated at start, a stored one loaded) go through here, so a sensor is calibrated and
checked one way: on its region's crop of the camera's frames, placed in the frame (the whole frame when it
has no region), its bundle refused where its region is not the board's.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.layout import FiberLayout
from optitac_edge.core.region import Region, bundle_region
from optitac_edge.errors import BundleError


def calibrate_sensor(rest: Sequence[np.ndarray] | np.ndarray, pixel_format: str, region: Region | None, *,
                     layout: FiberLayout | None = None, rotation_hint_deg: float = 0.0, mirror: bool = False,
                     times_ns: np.ndarray | None = None) -> CalibrationBundle:
    """The fiber map of a sensor from its camera's rest frames.

    Parameters
    ----------
    rest : sequence of ndarray
        The camera's whole rest frames (nothing touching the skins).
    pixel_format : str
    region : Region or None
        Where the board puts the sensor in the frame (None: the whole frame). With a region the map is made
        on its crop and placed in the frame.
    layout, rotation_hint_deg, mirror
        The fiber layout (None: the hexagonal default) and the orientation hint.
    times_ns : ndarray, shape (F,), int64, optional
        The frames' times (the rest noise is measured within runs of frames without a gap).
    """
    from optitac_edge.calibration.fibers import calibrate_fibers
    from optitac_edge.calibration.region import calibrate_region

    if region is not None:
        return calibrate_region(rest, pixel_format, region, layout=layout, rotation_hint_deg=rotation_hint_deg,
                                mirror=mirror, times_ns=times_ns)
    return calibrate_fibers(rest, pixel_format, layout=layout, rotation_hint_deg=rotation_hint_deg, mirror=mirror,
                            times_ns=times_ns)


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
