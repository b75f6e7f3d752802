"""Several fiber patches in one camera frame (one camera reading both fingers, fingertips and palm).

Each patch is its own simulated sensor (layout, skin, transmission pattern)
rendered at its region's size, with its own presses; the frame is the
camera's background with every patch pasted into its region. Calibrate each
patch on its region's crop and place its bundle in the frame
(:func:`optitac_edge.calibration.region.place_bundle`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from optitac_edge.core.layout import FiberLayout
from optitac_edge.core.region import Region
from optitac_edge.sim.optics import DEFAULT_OPTICS, CameraOptics
from optitac_edge.sim.render import SENSOR_SEED
from optitac_edge.sim.sensor import SimulatedSensor
from optitac_edge.sim.skin import Indenter


class PatchFrames:
    """Renders frames of ``width`` x ``height`` holding one simulated sensor in each region.

    Parameters
    ----------
    regions : sequence of Region
        One per patch; inside the frame, not overlapping.
    width, height : int
        The camera frame, px.
    layouts : sequence of FiberLayout, optional
        One per patch (default: the hexagonal 217-fiber array each).
    optics : CameraOptics
        Lens and illumination of every patch (its size is the region's).
    seed : int
        Frame noise; patch ``k`` is a physical sensor of its own (``SENSOR_SEED + k``).
    background_gray : int
        The frame outside the patches.

    Raises
    ------
    ValueError
        A region outside the frame, two regions overlapping, or a layout count that does not match.
    """

    def __init__(self, regions: Sequence[Region], width: int, height: int,
                 layouts: Sequence[FiberLayout | None] | None = None, optics: CameraOptics = DEFAULT_OPTICS,
                 seed: int = 0, background_gray: int = 8) -> None:
        self.regions = list(regions)
        layouts = list(layouts) if layouts is not None else [None] * len(self.regions)
        if len(layouts) != len(self.regions):
            raise ValueError(f"{len(self.regions)} regions but {len(layouts)} layouts")
        for k, r in enumerate(self.regions):
            if not r.inside(width, height):
                raise ValueError(f"patch {k}: region {r.to_dict()} leaves the {width}x{height} frame")
            for j in range(k):
                if r.overlaps(self.regions[j]):
                    raise ValueError(f"patches {j} and {k} overlap")
        self.width, self.height, self.rgb = width, height, optics.rgb
        self.background = int(background_gray)
        self.sensors = [SimulatedSensor(layout=lay, optics=replace(optics, width=r.width, height=r.height),
                                        seed=seed + 101 * k, sensor_seed=SENSOR_SEED + k)
                        for k, (r, lay) in enumerate(zip(self.regions, layouts))]

    @property
    def frame_shape(self) -> tuple[int, ...]:
        return (self.height, self.width, 3) if self.rgb else (self.height, self.width)

    def frame(self, presses: Sequence[Sequence[Indenter]] | None = None) -> np.ndarray:
        """One frame; ``presses[k]``: the indenters pressing patch ``k`` (default: none anywhere)."""
        presses = [()] * len(self.sensors) if presses is None else list(presses)
        if len(presses) != len(self.sensors):
            raise ValueError(f"{len(self.sensors)} patches but presses for {len(presses)}")
        out = np.full(self.frame_shape, self.background, dtype=np.uint8)
        for sensor, region, indenters in zip(self.sensors, self.regions, presses):
            out[region.y:region.y + region.height, region.x:region.x + region.width] = sensor.frame(indenters)
        return out


def crop(frames: np.ndarray, region: Region) -> np.ndarray:
    """``frames`` (shape (F, H, W[, 3])) cut to ``region``, C-contiguous (what a patch's calibration reads)."""
    return np.ascontiguousarray(frames[:, region.y:region.y + region.height, region.x:region.x + region.width])


@dataclass(frozen=True)
class PatchPlacement:
    """Patch ``index`` of ``frames``: a scenario rendered on it goes into whole camera frames
    (:func:`~optitac_edge.sim.scenarios.write_scenario`), the other patches at rest."""

    frames: PatchFrames
    index: int

    def __post_init__(self) -> None:
        if not 0 <= self.index < len(self.frames.regions):
            raise ValueError(f"patch {self.index} of {len(self.frames.regions)}")

    @property
    def region(self) -> Region:
        return self.frames.regions[self.index]

    def paste(self, patch_frame: np.ndarray) -> np.ndarray:
        """A whole camera frame: ``patch_frame`` in this patch's region, every other patch at rest."""
        out = self.frames.frame()
        r = self.region
        out[r.y:r.y + r.height, r.x:r.x + r.width] = patch_frame
        return out
