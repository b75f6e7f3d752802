"""Calibrate one sensor where its board puts it.

Both the command line (``calibrate fibers [--sensor ID]``) and the service (a missing bundle calibrated at
start) go through here, so a sensor is calibrated one way: on its region's crop of the camera's frames,
placed in the frame (the whole frame when it has no region). A bundle is checked against that region by
:func:`~optitac_edge.core.region.check_region` (at run time too: no calibration code is imported then).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.layout import FiberLayout
from optitac_edge.core.region import Region


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
