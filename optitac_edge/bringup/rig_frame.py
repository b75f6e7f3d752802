"""The rig-to-sensor transform, found from presses read through the bundle (pure functions).

A press with the tip at rig point ``p`` is read by the bundle at ``h(T(p))``,
where ``T`` is the rig-to-sensor transform (a rotation and a translation, mm
to mm) and ``h`` the layout symmetry the bundle's fiber map is off by (the
identity when it is right). Presses cannot tell ``h`` from a rotation of the
rig by a multiple of the layout's rotational step, so the rig is mounted as
docs/bring-up.md says: the sensor's marked +x within half a step (30 degrees
for the hexagon) of the rig's +X, skin facing the tool. Then ``T`` is the
fitted rotation within half a step, and whatever remains is ``h`` -- reported,
so ``calibrate orientation`` on the collected recording fixes the bundle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from optitac_edge.calibration.orientation import Symmetry

#: Registration presses must agree with the fitted transform to within this RMS, pitches (1 mm on the
#: paper's 1.5 mm array).
MAX_FIT_RMS_PITCH = 1.0 / 1.5


@dataclass(frozen=True)
class RigFrame:
    """Rig coordinates -> sensor frame.

    Attributes
    ----------
    origin_xy_mm : (float, float)
        The sensor's origin in rig coordinates.
    rotation_deg : float
        The sensor's +x, counter-clockwise from the rig's +X.
    surface_z_mm : float
        Rig z of the skin's surface (depth = surface_z - z).
    fit_rms_mm : float
        RMS residual of the registration presses.
    centroid_scale : float
        How far apart the bundle read the presses, as a fraction of how far apart the rig put them (a
        similarity fit's scale). An uncalibrated centroid -- a weighted mean over the fibers a press darkens --
        reads presses towards the array's middle (0.80 on a 61-fiber array at 4 mm pitch in the simulator)
        until ``calibrate centroid`` corrects it; the rig frame itself stays rigid (the rig's mm are mm).
    shape_rms_mm : float
        RMS residual of the registration presses once that scale is allowed: what the rig frame can be
        judged by before the centroid is calibrated.
    """

    origin_xy_mm: tuple[float, float]
    rotation_deg: float
    surface_z_mm: float
    fit_rms_mm: float = 0.0
    centroid_scale: float = 1.0
    shape_rms_mm: float = 0.0

    def to_sensor(self, xy: np.ndarray) -> np.ndarray:
        """Rig points (K, 2) -> sensor frame (K, 2), mm."""
        d = np.asarray(xy, dtype=np.float64).reshape(-1, 2) - np.asarray(self.origin_xy_mm)
        t = math.radians(-self.rotation_deg)
        c, s = math.cos(t), math.sin(t)
        return np.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]], axis=1)

    def to_rig(self, xy: np.ndarray) -> np.ndarray:
        """Sensor points (K, 2) -> rig coordinates (K, 2), mm."""
        p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        t = math.radians(self.rotation_deg)
        c, s = math.cos(t), math.sin(t)
        return np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]], axis=1) + np.asarray(
            self.origin_xy_mm)

    def angle_in_sensor(self, rig_angle_deg: float) -> float:
        """An indenter's angle as mounted on the rig, in the sensor frame, degrees."""
        return rig_angle_deg - self.rotation_deg

    def to_json(self) -> dict[str, float | list[float]]:
        return {"origin_xy_mm": [round(v, 4) for v in self.origin_xy_mm], "rotation_deg": round(self.rotation_deg, 4),
                "surface_z_mm": round(self.surface_z_mm, 4), "fit_rms_mm": round(self.fit_rms_mm, 4),
                "centroid_scale": round(self.centroid_scale, 4), "shape_rms_mm": round(self.shape_rms_mm, 4)}


def _inverse(h: Symmetry, xy: np.ndarray) -> np.ndarray:
    """``h^-1(xy)``: rotate back, then un-mirror."""
    t = math.radians(-h.rotation_deg)
    c, s = math.cos(t), math.sin(t)
    x, y = c * xy[:, 0] - s * xy[:, 1], s * xy[:, 0] + c * xy[:, 1]
    return np.stack([-x if h.mirror else x, y], axis=1)


def _procrustes(rig: np.ndarray, sensor: np.ndarray) -> tuple[float, np.ndarray, float, float, float]:
    """Of the best proper rigid map rig -> sensor: rotation angle (deg), translation and RMS; then the
    scale of the best similarity map with that rotation (about the presses' mean) and its RMS."""
    mr, ms = rig.mean(axis=0), sensor.mean(axis=0)
    a, b = rig - mr, sensor - ms
    angle = math.atan2(float(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0])), float(np.sum(a * b)))
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    t = ms - rot @ mr
    turned = a @ rot.T
    rms = float(np.sqrt(np.mean(np.sum((turned - b) ** 2, axis=1))))
    spread = float(np.sum(turned * turned))
    scale = float(np.sum(turned * b)) / spread if spread > 0 else 1.0
    shape_rms = float(np.sqrt(np.mean(np.sum((scale * turned - b) ** 2, axis=1))))
    return math.degrees(angle), t, rms, scale, shape_rms


def fit_rig_frame(rig_xy: np.ndarray, sensor_xy: np.ndarray, surface_z_mm: float,
                  symmetries: list[Symmetry], pitch_mm: float) -> tuple[RigFrame, Symmetry]:
    """The rig frame and the symmetry the bundle is off by, from registration presses.

    Parameters
    ----------
    rig_xy : ndarray, shape (K, 2)
        Where the tip pressed, rig coordinates, mm (K >= 3, not on one line).
    sensor_xy : ndarray, shape (K, 2)
        Where the bundle read those presses (raw centroids), mm.
    symmetries : list of Symmetry
        The layout's (:func:`~optitac_edge.calibration.orientation.layout_symmetries`).
    pitch_mm : float
        The layout's fiber pitch.

    Returns
    -------
    RigFrame, Symmetry
        ``T`` with its rotation within half the layout's rotational step of 0,
        and ``h`` (identity: the bundle is right).

    Raises
    ------
    ValueError
        If the presses do not fit any rigid map within :data:`MAX_FIT_RMS_PITCH` pitches.
    """
    rig = np.asarray(rig_xy, dtype=np.float64).reshape(-1, 2)
    seen = np.asarray(sensor_xy, dtype=np.float64).reshape(-1, 2)
    rotations = sorted({round(h.rotation_deg, 6) for h in symmetries if not h.mirror})
    step = min((r for r in rotations if r > 0), default=360.0)
    best: tuple[float, RigFrame, Symmetry] | None = None
    for h in symmetries:
        angle, t, rms, scale, shape_rms = _procrustes(rig, _inverse(h, seen))
        if not -step / 2 - 1e-9 < angle <= step / 2 + 1e-9:
            continue
        # sensor = R(angle) rig + t  =>  origin (rig point mapped to 0) = -R(-angle) t
        c, s = math.cos(math.radians(-angle)), math.sin(math.radians(-angle))
        origin = (-(c * t[0] - s * t[1]), -(s * t[0] + c * t[1]))
        # the sensor's +x is rotated by -angle from the rig's +X (sensor = R(angle) rig)
        frame = RigFrame(origin_xy_mm=(float(origin[0]), float(origin[1])), rotation_deg=-angle,
                         surface_z_mm=surface_z_mm, fit_rms_mm=rms, centroid_scale=scale, shape_rms_mm=shape_rms)
        if best is None or rms < best[0]:
            best = (rms, frame, h)
    if best is None or best[1].shape_rms_mm > MAX_FIT_RMS_PITCH * pitch_mm:  # judged with the centroid's scale
        raise ValueError(f"the registration presses fit no rigid placement of the sensor "
                         f"(best RMS {best[1].shape_rms_mm if best else math.inf:.2f} mm): is the sensor fixed to "
                         "the rig?")
    return best[1], best[2]
