"""The layout's symmetries, and which one a bundle's fiber map is off by, from presses.

A hexagonal fiber array looks the same in rest frames after any of its 12
symmetries (6 rotations by 60 degrees, each with or without a mirror), so
fiber registration cannot tell which fiber is which up to a symmetry: the
orientation hint decides it, and a wrong hint gives a fiber map that is
internally perfect and wrong. Presses of known position decide it: a press at
``p`` read through a fiber map off by the symmetry ``h`` is found at ``h(p)``.

Conventions: a symmetry ``h`` maps layout point ``x`` to ``R(theta) M^b x``
(``M`` negates x, then a counter-clockwise rotation by ``theta``), the same
order as :class:`~optitac_edge.core.image_transform.ImageTransform`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.corrections import CENTROID_KEY, SHAPES_KEY, WIDTH_KEY
from optitac_edge.core.fiber_table import FiberTable
from optitac_edge.core.layout import FiberLayout
from optitac_edge.core.levels import FIBER_ARRAYS

#: Two layout points closer than this fraction of the pitch are the same point.
MATCH_TOL_PITCH = 0.1
#: The best symmetry is accepted only if its centroid RMS error is below this, pitches (2 mm on the
#: paper's 1.5 mm array: an absolute 2 mm refused a 4 mm-pitch sensor whose presses fitted to 0.76 pitch)...
ACCEPT_RMSE_PITCH = 2.0 / 1.5
#: ... and the second best is at least this much worse (pitches, 1 mm on the paper's array), and this many
#: times worse.
MARGIN_PITCH = 1.0 / 1.5
MARGIN_RATIO = 2.0
#: ... or, with many presses, the evidence for the best over the second best is this many to one: the
#: likelihood ratio of Gaussian errors, ``K ln(MSE2 / MSE1)`` over K presses, at least ``ln`` of it (17
#: noisy presses of a real 4 mm array fitted 4.2 mm against 7.2 mm: a ratio under 2, a likelihood 10^7 to one).
EVIDENCE_ODDS = 1000.0
#: Key of the orientation record in a bundle's ``extra_meta``.
ORIENTATION_KEY = "orientation"


@dataclass(frozen=True, eq=False)
class Symmetry:
    """One symmetry of a layout.

    Attributes
    ----------
    rotation_deg : float
        Counter-clockwise rotation after the optional mirror, degrees in [0, 360).
    mirror : bool
        x is negated before the rotation.
    permutation : ndarray, shape (N,), int64
        ``permutation[i]`` is the fiber at ``h(x_i)``.
    """

    rotation_deg: float
    mirror: bool
    permutation: np.ndarray

    @property
    def is_identity(self) -> bool:
        return not self.mirror and bool(np.all(self.permutation == np.arange(self.permutation.size)))

    @property
    def label(self) -> str:
        """E.g. ``rotated 120°, mirrored`` or ``as it is``."""
        parts = [] if abs(self.rotation_deg) < 1e-6 else [f"rotated {self.rotation_deg:.0f}°"]
        if self.mirror:
            parts.append("mirrored")
        return ", ".join(parts) or "as it is"

    def apply(self, xy_mm: np.ndarray) -> np.ndarray:
        """``h(xy)`` for points of shape (K, 2), mm."""
        xy = np.asarray(xy_mm, dtype=np.float64).reshape(-1, 2)
        x = -xy[:, 0] if self.mirror else xy[:, 0]
        t = math.radians(self.rotation_deg)
        c, s = math.cos(t), math.sin(t)
        return np.stack([c * x - s * xy[:, 1], s * x + c * xy[:, 1]], axis=1)


def layout_symmetries(layout: FiberLayout) -> list[Symmetry]:
    """Every rotation and mirror about the layout's origin that maps its fibers onto themselves.

    The identity comes first. 12 for the default hexagon; a custom layout
    has whatever symmetries its fiber positions have (at least the identity).
    """
    xy = np.asarray(layout.xy_mm, dtype=np.float64)
    tol = MATCH_TOL_PITCH * layout.pitch_mm
    tree = cKDTree(xy)
    r = np.hypot(xy[:, 0], xy[:, 1])
    ref = int(np.argmax(r))
    found: list[Symmetry] = []
    for mirror in (False, True):
        ref_xy = np.array([-xy[ref, 0] if mirror else xy[ref, 0], xy[ref, 1]])
        for q in np.flatnonzero(np.abs(r - r[ref]) < tol):
            theta = (math.degrees(math.atan2(xy[q, 1], xy[q, 0]) - math.atan2(ref_xy[1], ref_xy[0]))) % 360.0
            theta = 0.0 if min(theta, 360.0 - theta) < 1e-6 else theta
            h = Symmetry(theta, mirror, np.zeros(0, np.int64))
            d, idx = tree.query(h.apply(xy))
            if np.all(d < tol) and np.unique(idx).size == idx.size:
                found.append(replace(h, permutation=idx.astype(np.int64)))
    found.sort(key=lambda h: (h.mirror, round(h.rotation_deg, 6)))
    return found


@dataclass(frozen=True)
class OrientationFit:
    """Which symmetry of the layout maps true press positions onto the measured ones.

    Attributes
    ----------
    symmetry : Symmetry or None
        The symmetry the bundle's fiber map is off by (identity: it is right);
        None when the presses cannot tell (see ``reason``).
    rmse_mm : tuple of float
        Centroid RMS error under each symmetry, in :func:`layout_symmetries` order, mm.
    labels : tuple of str
        The symmetries' labels, same order.
    presses : int
        Presses (or frames) used.
    reason : str
        Why no symmetry was chosen ('' when one was).
    """

    symmetry: Symmetry | None
    rmse_mm: tuple[float, ...]
    labels: tuple[str, ...]
    presses: int
    reason: str = ""

    @property
    def best_rmse_mm(self) -> float:
        return min(self.rmse_mm)

    @property
    def runner_up(self) -> tuple[str, float]:
        order = np.argsort(self.rmse_mm)
        k = int(order[1]) if len(order) > 1 else int(order[0])
        return self.labels[k], self.rmse_mm[k]


def fit_orientation(measured_mm: np.ndarray, true_mm: np.ndarray, symmetries: list[Symmetry], pitch_mm: float,
                    accept_mm: float | None = None, margin_mm: float | None = None,
                    margin_ratio: float = MARGIN_RATIO) -> OrientationFit:
    """Choose the symmetry ``h`` with ``measured ≈ h(true)``, or refuse when the presses can't tell.

    Parameters
    ----------
    measured_mm, true_mm : ndarray, shape (K, 2), float64
        Centroids read through the bundle (raw, without a centroid map) and the
        true press positions, mm, sensor frame.
    symmetries : list of Symmetry
        From :func:`layout_symmetries`.
    pitch_mm : float
        The layout's fiber pitch: the gates below are in pitches.
    accept_mm, margin_mm : float, optional
        Default :data:`ACCEPT_RMSE_PITCH` and :data:`MARGIN_PITCH` pitches.

    Notes
    -----
    Accepted when the best RMS error is below ``accept_mm`` and every
    other symmetry's is at least ``margin_mm`` larger and either ``margin_ratio``
    times as large or worse by the evidence of :data:`EVIDENCE_ODDS` to one over the presses
    (``K ln(MSE2 / MSE1)``). Presses on the array's centre or only along one mirror axis fit
    several symmetries equally well and are refused.
    """
    accept_mm = ACCEPT_RMSE_PITCH * pitch_mm if accept_mm is None else accept_mm
    margin_mm = MARGIN_PITCH * pitch_mm if margin_mm is None else margin_mm
    m = np.asarray(measured_mm, dtype=np.float64).reshape(-1, 2)
    t = np.asarray(true_mm, dtype=np.float64).reshape(-1, 2)
    ok = np.all(np.isfinite(m), axis=1) & np.all(np.isfinite(t), axis=1)
    m, t = m[ok], t[ok]
    labels = tuple(h.label for h in symmetries)
    if m.shape[0] == 0:
        return OrientationFit(None, tuple(math.inf for _ in symmetries), labels, 0, "no detected presses")
    rmse = tuple(float(np.sqrt(np.mean(np.sum((m - h.apply(t)) ** 2, axis=1)))) for h in symmetries)
    order = np.argsort(rmse)
    best = int(order[0])
    fit = OrientationFit(symmetries[best], rmse, labels, int(m.shape[0]))
    if rmse[best] > accept_mm:
        return replace(fit, symmetry=None, reason=(
            f"no orientation fits these presses (best {labels[best]}: RMS {rmse[best]:.2f} mm = "
            f"{rmse[best] / pitch_mm:.2f} pitch, accepted below {accept_mm / pitch_mm:.2f} pitch): check that the "
            "truth's x_mm, y_mm are in the sensor frame (mm from the central fiber, +x along the rows of fibers) "
            "and that the bundle's layout is this sensor's"))
    if len(order) > 1:
        second = rmse[int(order[1])]
        evidence = m.shape[0] * 2.0 * math.log(max(second, 1e-12) / max(rmse[best], 1e-12))
        if second < rmse[best] + margin_mm or (second < margin_ratio * rmse[best]
                                               and evidence < math.log(EVIDENCE_ODDS)):
            return replace(fit, symmetry=None, reason=(
                f"the presses cannot tell '{labels[best]}' ({rmse[best]:.2f} mm) from "
                f"'{labels[int(order[1])]}' ({second:.2f} mm): press away from the centre and not only "
                "along one line through it"))
    return fit


def reorient_table(table: FiberTable, permutation: np.ndarray) -> FiberTable:
    """The fiber table with fiber ``i`` taking the pixels that were fiber ``permutation[i]``'s."""
    starts, index = table.pixel_start, table.pixel_index
    groups = [index[starts[j]:starts[j + 1]] for j in permutation]
    new_start = np.zeros(permutation.size + 1, dtype=np.int64)
    np.cumsum([g.size for g in groups], out=new_start[1:])
    return replace(table, pixel_index=np.concatenate(groups).astype(index.dtype),
                   pixel_start=new_start, centroid_px=table.centroid_px[permutation].copy(),
                   dead=table.dead[permutation].copy())


def reorient_bundle(bundle: CalibrationBundle, h: Symmetry, evidence: str) -> CalibrationBundle:
    """The bundle with its fiber map corrected by the symmetry ``h`` it was found to be off by.

    The identity changes nothing but the record: the orientation was checked
    (:func:`mark_verified`). Otherwise fiber ``i`` takes the pixels of the fiber at ``h(x_i)``; the transform
    becomes ``T ∘ h``; each fiber's levels (noise, drift) go with its pixels. Models fitted through the wrong fiber map (centroid,
    width, shapes) are removed: calibrate them again. The orientation record
    (``extra_meta['orientation']``) says it was verified and how.
    """
    if h.is_identity:
        return mark_verified(bundle, evidence)
    t = bundle.transform
    rotation = (t.rotation_deg - h.rotation_deg) if t.mirror else (t.rotation_deg + h.rotation_deg)
    transform = replace(t, rotation_deg=rotation % 360.0, mirror=t.mirror != h.mirror)
    stale = (CENTROID_KEY, WIDTH_KEY, SHAPES_KEY)
    extra_meta = {k: v for k, v in bundle.extra_meta.items()
                  if k not in stale and k not in ("centroid_fit", "width_fit", "shapes_fit")}
    extra_arrays = {k: v[h.permutation] if k in FIBER_ARRAYS else v for k, v in bundle.extra_arrays.items()
                    if not k.startswith(tuple(f"{s}/" for s in stale)) and not k.startswith("report/")}
    extra_meta[ORIENTATION_KEY] = {"verified": True, "corrected": h.label, "evidence": evidence}
    return bundle.with_updates(fibers=reorient_table(bundle.fibers, h.permutation), transform=transform,
                               extra_meta=extra_meta, extra_arrays=extra_arrays)


def mark_verified(bundle: CalibrationBundle, evidence: str) -> CalibrationBundle:
    """The bundle with its orientation recorded as checked against presses (``evidence`` says which)."""
    return bundle.with_updates(extra_meta={**bundle.extra_meta,
                                           ORIENTATION_KEY: {"verified": True, "corrected": "",
                                                             "evidence": evidence}})


def is_verified(bundle: CalibrationBundle) -> bool:
    """True when the bundle's orientation was checked against presses."""
    record = bundle.extra_meta.get(ORIENTATION_KEY)
    return isinstance(record, dict) and record.get("verified") is True


#: A fiber map rebuilt from rest frames keeps the orientation presses settled for the one it replaces when it is
#: turned as that one was: the same mirror, within half the hexagon's smallest symmetric turn, degrees.
KEEP_TURN_DEG = 30.0


def settles(old: CalibrationBundle, layout: FiberLayout) -> bool:
    """``old``'s orientation was settled by presses (orient, calibrate orientation, fiducials) for ``layout``: a
    fiber map of ``layout`` rebuilt to replace it may take its rotation and mirror as the hint."""
    xy = old.layout.xy_mm
    return is_verified(old) and xy.shape == layout.xy_mm.shape and bool(np.allclose(xy, layout.xy_mm))


def keep_orientation(old: CalibrationBundle, new: CalibrationBundle) -> CalibrationBundle | None:
    """``new`` with ``old``'s settled orientation recorded (the evidence says it was kept) when its fiber map is
    turned as ``old``'s was (:data:`KEEP_TURN_DEG`); None when it is not (the orientation must be settled again).
    """
    turn = (new.transform.rotation_deg - old.transform.rotation_deg + 180.0) % 360.0 - 180.0
    if new.transform.mirror != old.transform.mirror or not abs(turn) < KEEP_TURN_DEG:
        return None
    evidence = old.extra_meta[ORIENTATION_KEY].get("evidence", "presses")
    return mark_verified(new, f"kept from the bundle this one replaced ({evidence})")


#: Fiducials decide a symmetry when the next best scores this many level standard deviations worse.
FIDUCIAL_MARGIN = 1.0


def fiducial_orientation(levels: np.ndarray, layout: FiberLayout, symmetries: list[Symmetry]) -> OrientationFit:
    """The symmetry under which fibers dark and bright by design read darkest and brightest.

    Parameters
    ----------
    levels : ndarray, shape (N,), float
        Each fiber's mean gray level in the rest frames, through the bundle's
        fiber map (0 for fibers found dead).
    layout : FiberLayout
        With ``fiducial`` set.

    Notes
    -----
    Score of ``h``: mean standardised level of the fibers ``h`` puts on the
    dark fiducials minus that on the bright ones (lowest wins); the best must
    beat the next by ``FIDUCIAL_MARGIN`` standard deviations, else the
    fiducials are as symmetric as the layout and the fit refuses.
    """
    marks = layout.fiducial
    labels = tuple(h.label for h in symmetries)
    if marks is None or not np.any(marks):
        return OrientationFit(None, tuple(math.inf for _ in symmetries), labels, 0, "the layout has no fiducials")
    z = (levels - levels.mean()) / max(float(levels.std()), 1e-9)
    dark, bright = np.flatnonzero(marks < 0), np.flatnonzero(marks > 0)
    scores = []
    for h in symmetries:
        seen = z[h.permutation]
        scores.append((seen[dark].mean() if dark.size else 0.0) - (seen[bright].mean() if bright.size else 0.0))
    order = np.argsort(scores)
    best = int(order[0])
    fit = OrientationFit(symmetries[best], tuple(float(s) for s in scores), labels, int(dark.size + bright.size))
    if len(order) > 1 and scores[int(order[1])] - scores[best] < FIDUCIAL_MARGIN:
        return replace(fit, symmetry=None, reason=(
            f"the fiducials cannot tell '{labels[best]}' from '{labels[int(order[1])]}' "
            "(they are as symmetric as the layout, or not dark/bright in the rest frames)"))
    return fit
