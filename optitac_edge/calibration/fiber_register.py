"""Register detected blobs to the CAD layout: fit the image transform, assign fibers.

Coarse estimate, then iterated matching and refitting:

1. pitch in px = median nearest-neighbour distance of the blob centroids -> scale;
2. lattice angle from the nearest-neighbour vectors (a hexagonal lattice is
   60-degree periodic: the 6th circular moment gives the angle modulo 60);
   ``rotation_hint_deg`` picks the branch, so the hint must be within +-20
   (strictly: +-30) degrees of the truth;
3. centre: lattice points around the blob nearest the centroid of all blobs are
   tried as the central fiber; the one that predicts the most blobs is kept;
4. iterate: predict every layout fiber's image position, match one-to-one with
   :func:`scipy.optimize.linear_sum_assignment` gated at ``gate_pitch`` pitches,
   refit rotation, scale, centre and radial ``k1`` by least squares on the
   matched pairs; stop when the assignment no longer changes.

The hexagonal layout is itself 60-degree symmetric, so a hint more than 30
degrees off silently assigns every fiber to its neighbour by a lattice rotation;
it cannot be detected from the image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares, linear_sum_assignment
from scipy.spatial import cKDTree

from optitac_edge.core.image_transform import ImageTransform
from optitac_edge.core.layout import FiberLayout
from optitac_edge.errors import FiberMapError


@dataclass(frozen=True)
class RegisterParams:
    """Parameters of :func:`register_blobs`.

    Attributes
    ----------
    gate_pitch : float
        A blob matches a predicted fiber position only within this many pitches.
    max_iter : int
        Maximum match/refit iterations.
    centre_search_rings : int
        Lattice points within this many rings of the blob nearest the centroid of
        all blobs are tried as the central fiber.
    fit_k1 : bool
        Fit the radial distortion ``k1`` (else it stays 0).
    """

    gate_pitch: float = 0.35
    max_iter: int = 20
    centre_search_rings: int = 2
    fit_k1: bool = True


@dataclass(frozen=True, eq=False)
class Registration:
    """Result of :func:`register_blobs`.

    Attributes
    ----------
    transform : ImageTransform
        Fitted layout -> image transform.
    fiber_blob : ndarray, shape (N,), int64
        Blob index matched to each layout fiber, -1 if none (dead).
    blob_fiber : ndarray, shape (K,), int64
        Layout fiber index of each blob, -1 if it fits none (unmatched).
    residual_px : ndarray, shape (N,), float64
        Distance of each matched blob from its fiber's predicted position, px; NaN if dead.
    pitch_px : float
        Nominal fiber pitch in the image, px (``scale * layout pitch``).
    """

    transform: ImageTransform
    fiber_blob: np.ndarray
    blob_fiber: np.ndarray
    residual_px: np.ndarray
    pitch_px: float

    @property
    def n_found(self) -> int:
        return int(np.count_nonzero(self.fiber_blob >= 0))

    @property
    def dead(self) -> np.ndarray:
        """Layout indices of fibers without a blob, shape (D,), int64."""
        return np.flatnonzero(self.fiber_blob < 0)

    @property
    def unmatched(self) -> np.ndarray:
        """Indices of blobs matched to no fiber, shape (U,), int64."""
        return np.flatnonzero(self.blob_fiber < 0)

    @property
    def rms_px(self) -> float:
        """RMS residual of the matched blobs, px (NaN if none)."""
        r = self.residual_px[self.fiber_blob >= 0]
        return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")

    @property
    def rms_pitch(self) -> float:
        """RMS residual in pitch units."""
        return self.rms_px / self.pitch_px


def lattice_angle_deg(points_px: np.ndarray, pitch_px: float) -> float:
    """Hexagonal lattice direction of image points, degrees in [0, 60), layout frame (+y up).

    Parameters
    ----------
    points_px : ndarray, shape (K, 2), float64
        Points (col, row), px.
    pitch_px : float
        Approximate lattice pitch, px (neighbour vectors within 1.3 pitch count).
    """
    tree = cKDTree(points_px)
    pairs = tree.query_pairs(1.3 * pitch_px, output_type="ndarray")
    d = points_px[pairs[:, 1]] - points_px[pairs[:, 0]]
    phi = np.arctan2(-d[:, 1], d[:, 0])  # image rows grow downwards
    m = np.exp(6j * phi).mean()
    return float(np.degrees(np.angle(m)) / 6.0) % 60.0


def _match(pred: np.ndarray, blobs: np.ndarray, gate: float) -> tuple[np.ndarray, np.ndarray]:
    """One-to-one gated matching; returns (fiber indices, blob indices) of the pairs."""
    tree = cKDTree(blobs)
    pairs = tree.query_ball_point(pred, gate)
    cost = np.full((pred.shape[0], blobs.shape[0]), 1e6)
    for i, js in enumerate(pairs):  # per fiber (~N), not per pixel
        if js:
            cost[i, js] = np.linalg.norm(blobs[js] - pred[i], axis=1)
    fi, bj = linear_sum_assignment(cost)
    ok = cost[fi, bj] < gate
    return fi[ok], bj[ok]


def _fit(t: ImageTransform, xy_mm: np.ndarray, uv: np.ndarray, fit_k1: bool) -> ImageTransform:
    """Least-squares refit of rotation, scale, centre (and k1) to matched pairs."""

    def make(p: np.ndarray) -> ImageTransform:
        return replace(
            t,
            rotation_deg=math.degrees(p[0]),
            scale_px_per_mm=math.exp(p[1]),
            cx=p[2],
            cy=p[3],
            k1=p[4] if fit_k1 else 0.0,
        )

    def resid(p: np.ndarray) -> np.ndarray:
        return (make(p).layout_to_image(xy_mm) - uv).ravel()

    p0 = np.array([math.radians(t.rotation_deg), math.log(t.scale_px_per_mm), t.cx, t.cy, t.k1])
    lo = np.array([-np.inf, -np.inf, -np.inf, -np.inf, -0.5])
    hi = np.array([np.inf, np.inf, np.inf, np.inf, 0.5])
    p0[4] = np.clip(p0[4], -0.49, 0.49)
    sol = least_squares(resid, p0, bounds=(lo, hi), x_scale="jac")
    t_new = make(sol.x)
    return replace(t_new, rotation_deg=t_new.rotation_deg % 360.0)


def _refine(
    t: ImageTransform, layout: FiberLayout, blobs: np.ndarray, params: RegisterParams
) -> tuple[ImageTransform, np.ndarray, np.ndarray]:
    """Iterate match -> refit until the assignment is stable."""
    pitch_px = t.scale_px_per_mm * layout.pitch_mm
    fi = bj = np.zeros(0, dtype=np.int64)
    for _ in range(params.max_iter):
        gate = params.gate_pitch * pitch_px
        new_fi, new_bj = _match(t.layout_to_image(layout.xy_mm), blobs, gate)
        if np.array_equal(new_fi, fi) and np.array_equal(new_bj, bj):
            break
        fi, bj = new_fi, new_bj
        if fi.size < 4:
            break
        t = _fit(t, layout.xy_mm[fi], blobs[bj], params.fit_k1 and fi.size >= 12)
        pitch_px = t.scale_px_per_mm * layout.pitch_mm
    return t, fi, bj


def register_blobs(
    centroids_px: np.ndarray,
    layout: FiberLayout,
    rotation_hint_deg: float = 0.0,
    mirror: bool = False,
    params: RegisterParams = RegisterParams(),
) -> Registration:
    """Fit the layout -> image transform to blob centroids and assign blobs to fibers.

    Parameters
    ----------
    centroids_px : ndarray, shape (K, 2), float64
        Blob centroids (col, row), px.
    layout : FiberLayout
        The CAD layout (its origin must be a fiber, the array's centre).
    rotation_hint_deg : float
        The array appears rotated counter-clockwise by about this angle in the
        image, degrees; must be within +-20 degrees of the truth.
    mirror : bool
        Layout x is negated before rotation (known from the optics).
    params : RegisterParams
        Matching parameters.

    Raises
    ------
    FiberMapError
        If there are too few blobs to estimate a lattice.
    """
    uv = np.asarray(centroids_px, dtype=np.float64).reshape(-1, 2)
    n, k = layout.n_fibers, uv.shape[0]
    if k < 7:
        raise FiberMapError(f"found {k} of {n} fibers in the rest frames (is the LED on?)")
    nn, _ = cKDTree(uv).query(uv, k=2)
    pitch_px = float(np.median(nn[:, 1]))
    if not pitch_px > 0:
        raise FiberMapError("blob centroids coincide; cannot estimate the fiber pitch")
    scale = pitch_px / layout.pitch_mm
    alpha = lattice_angle_deg(uv, pitch_px)
    rot = alpha + 60.0 * round((rotation_hint_deg - alpha) / 60.0)
    origin = int(np.argmin(np.linalg.norm(layout.xy_mm, axis=1)))
    xy0 = layout.xy_mm - layout.xy_mm[origin]
    tree = cKDTree(uv)
    # Centre candidates: lattice points (up to 2 rings) around the blob nearest the
    # centroid of all blobs, nearest first; works even if the central fiber is dead.
    mean = uv.mean(axis=0)
    _, b0 = tree.query(mean)
    t_rot = ImageTransform(rot % 360.0, scale, 0.0, 0.0, mirror, 0.0, layout.radius_mm)
    ring = params.centre_search_rings
    steps = np.array(
        [
            (a, b)
            for a in range(-ring, ring + 1)
            for b in range(-ring, ring + 1)
            if abs(a + b) <= ring
        ],
        dtype=np.float64,
    )
    e = np.array([[1.0, 0.0], [0.5, math.sqrt(3.0) / 2.0]]) * pitch_px
    offs = t_rot.layout_to_image(steps @ e / scale)  # lattice offsets in px (distortion-free)
    cands = uv[b0] + offs
    cands = cands[np.argsort(np.linalg.norm(cands - mean, axis=1), kind="stable")]
    best: tuple[int, ImageTransform] | None = None
    for c in cands:
        t = replace(t_rot, cx=float(c[0]), cy=float(c[1]))
        d, _ = tree.query(t.layout_to_image(xy0))
        score = int(np.count_nonzero(d < 0.4 * pitch_px))
        if best is None or score > best[0]:
            best = (score, t)
    assert best is not None
    # The candidate blob sits on layout fiber `origin`; shift to the layout origin.
    t0 = best[1]
    if np.any(layout.xy_mm[origin] != 0.0):
        shift = t0.layout_to_image(-layout.xy_mm[origin][None])[0] - np.array([t0.cx, t0.cy])
        t0 = replace(t0, cx=t0.cx + shift[0], cy=t0.cy + shift[1])
    t, fi, bj = _refine(t0, layout, uv, params)
    fiber_blob = np.full(n, -1, dtype=np.int64)
    blob_fiber = np.full(k, -1, dtype=np.int64)
    fiber_blob[fi], blob_fiber[bj] = bj, fi
    residual = np.full(n, np.nan)
    residual[fi] = np.linalg.norm(t.layout_to_image(layout.xy_mm[fi]) - uv[bj], axis=1)
    return Registration(t, fiber_blob, blob_fiber, residual, t.scale_px_per_mm * layout.pitch_mm)
