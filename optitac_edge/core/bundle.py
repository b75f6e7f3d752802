"""The calibration bundle in memory: everything the runtime pipeline needs, checked for consistency.

Its file format (a versioned ``.npz`` with a digest, written atomically) is
:mod:`optitac_edge.io.bundle_file`; the builders are in :mod:`optitac_edge.calibration`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from optitac_edge.core.fiber_table import FiberTable
from optitac_edge.core.grid import SurfaceGrid
from optitac_edge.core.image_transform import ImageTransform
from optitac_edge.core.layout import FiberLayout
from optitac_edge.core.options import ContactOptions, ContactThresholds
from optitac_edge.core.surface import SurfaceFactors

#: Leading contact-free frames averaged into the baseline (the paper's 5).
BASELINE_FRAMES = 5
#: Most frames a bundle may average into the baseline (a few seconds at 240 fps).
MAX_BASELINE_FRAMES = 1000
#: Largest difference between the factored and the dense surface of a test vector accepted
#: by :class:`CalibrationBundle`, relative to the largest ``|A| @ |v|`` (float32 rounding: ~1e-7).
FACTOR_CHECK_TOL = 1e-4


@dataclass(frozen=True, eq=False)
class CalibrationBundle:
    """Everything the runtime pipeline needs, as loaded from one file.

    Attributes
    ----------
    layout : FiberLayout
        The sensor's CAD layout (N fibers).
    transform : ImageTransform
        Fitted layout -> image transform.
    fibers : FiberTable
        Fiber lookup table; also records the frame size and pixel format.
    grid : SurfaceGrid
        The interpolation mesh.
    interpolation : ndarray, shape (grid.n ** 2, N), float32
        Surface = ``interpolation @ fiber_values`` (row-major mesh order);
        rows of mesh points outside the array are zero.
    thresholds : ContactThresholds
        The paper's threshold and minimum area.
    options : ContactOptions
        Improvements beyond the paper and the noise measured at calibration.
    fiber_map_report : dict
        JSON-able summary of the fiber calibration.
    extra_arrays : mapping of str to ndarray
        Later calibration models (numeric arrays only).
    extra_meta : dict
        JSON-able parameters of later calibration models.
    source : str
        The file the bundle was read from, "" when made in memory (not stored in the file).
    surface_factors : SurfaceFactors or None
        Exact factorisation of ``interpolation`` (fast runtime surface, see
        :class:`~optitac_edge.core.surface.TriangleSurface`); None for bundles written
        without it (the runtime then uses the dense matrix).

    Raises
    ------
    ValueError
        If the arrays disagree on the number of fibers or mesh cells, or the
        surface factors do not reproduce ``interpolation``.
    """

    layout: FiberLayout
    transform: ImageTransform
    fibers: FiberTable
    grid: SurfaceGrid
    interpolation: np.ndarray
    thresholds: ContactThresholds = field(default_factory=ContactThresholds)
    options: ContactOptions = field(default_factory=ContactOptions)
    baseline_frames: int = BASELINE_FRAMES
    fiber_map_report: dict[str, Any] = field(default_factory=dict)
    extra_arrays: Mapping[str, np.ndarray] = field(default_factory=dict)
    extra_meta: dict[str, Any] = field(default_factory=dict)
    created_utc: str = ""
    calibration_id: str = ""
    surface_factors: SurfaceFactors | None = None
    #: The file it was read from ("" for a bundle made in memory), for the lines that name it.
    source: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        n = self.layout.n_fibers
        if self.fibers.n_fibers != n:
            raise ValueError(f"fiber table has {self.fibers.n_fibers} fibers, layout {n}")
        if self.interpolation.shape != (self.grid.n * self.grid.n, n):
            raise ValueError(f"interpolation matrix has shape {self.interpolation.shape}")
        if self.interpolation.dtype.kind != "f" or not np.all(np.isfinite(self.interpolation)):
            raise ValueError("interpolation matrix must be finite floating point")
        _check_weights(self.interpolation)
        b = self.baseline_frames
        if not isinstance(b, int) or isinstance(b, bool) or not 1 <= b <= MAX_BASELINE_FRAMES:
            raise ValueError(f"baseline_frames must be an integer in 1..{MAX_BASELINE_FRAMES}, got {b!r}")
        for name, arr in self.extra_arrays.items():
            a = np.asarray(arr)
            if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
                raise ValueError(f"extra array {name!r} holds non-finite values")
            if name.startswith("levels/") and (a.shape != (n,) or a.dtype.kind != "f" or np.any(a < 0)):
                raise ValueError(f"extra array {name!r} must hold {n} values >= 0 (one a fiber)")
        levels = self.extra_meta.get("levels", {})
        if not isinstance(levels, dict) or any(
                not isinstance(levels.get(k, 0), int) or isinstance(levels.get(k, 0), bool) or levels.get(k, 0) < 0
                for k in ("noise_samples", "drift_samples")):
            raise ValueError("extra levels: noise_samples and drift_samples must be whole numbers >= 0")
        if self.surface_factors is not None:
            _check_factors(self.surface_factors, self.interpolation)

    def with_updates(self, **changes: Any) -> CalibrationBundle:
        """A copy with some fields replaced (e.g. a new calibration model)."""
        return replace(self, **changes)


#: A surface interpolation's weights: each at most this large (Clough-Tocher overshoots to ~1.004 and -0.11)...
MAX_WEIGHT = 4.0
#: ... and each mesh cell's adding up to at most 1 in size (Clough-Tocher: 0 outside the array, 1 inside: it
#: reproduces a constant), to this much.
WEIGHT_SUM_TOL = 1e-3


def _check_weights(matrix: np.ndarray) -> None:
    """Raise ValueError unless ``matrix`` is an interpolation's: bounded weights, each row adding up to at most
    1 in size (a surface no larger than the fibers' values)."""
    sums = np.abs(np.asarray(matrix, dtype=np.float64).sum(axis=1))
    if float(np.abs(matrix).max(initial=0.0)) > MAX_WEIGHT or np.any(sums > 1.0 + WEIGHT_SUM_TOL):
        raise ValueError(f"interpolation matrix: a mesh cell's weights must each lie within +-{MAX_WEIGHT:g} and "
                         f"add up to at most 1 (got weights up to {float(np.abs(matrix).max()):.3g}, sums up to "
                         f"{float(sums.max()):.3g})")


def _check_factors(factors: SurfaceFactors, matrix: np.ndarray) -> None:
    """Raise ValueError unless ``factors`` has ``matrix``'s shape and reproduces it on a test vector."""
    if (factors.n_cells, factors.n_fibers) != matrix.shape:
        raise ValueError(f"surface factors are for {factors.n_cells} mesh cells and {factors.n_fibers} "
                         f"fibers, the interpolation matrix has shape {matrix.shape}")
    v = np.cos(0.7 * np.arange(matrix.shape[1])).astype(np.float32)  # deterministic, all fibers
    w = factors.vertex_operator @ v
    factored = np.einsum("ck,ck->c", factors.cell_weights, w[factors.cell_columns])
    matrix = np.asarray(matrix, dtype=np.float32)
    scale = float((np.abs(matrix) @ np.abs(v)).max(initial=0.0))
    err = float(np.abs(factored - matrix @ v).max(initial=0.0))
    if not err <= FACTOR_CHECK_TOL * max(scale, float(np.finfo(np.float32).tiny)):
        raise ValueError(f"surface factors do not reproduce the interpolation matrix "
                         f"(difference {err:.3g}, scale {scale:.3g})")


