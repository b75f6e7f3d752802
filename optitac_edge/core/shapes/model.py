"""The runtime shape model in closed form: a Gaussian mixture with class-labelled components.

Both classifier kinds reduce to it. The paper's unsupervised GMM has one
component per cluster, each cluster mapped to a shape; the supervised
alternative has 1-3 components per class, weighted by the class prior. The
class posterior is the sum of the posteriors of the class's components.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from optitac_edge.core.shapes.features import LOG_HU_CAP, N_FEATURES, N_HU, Q4_FLOOR, Q4_INDEX

SHAPE_MODEL_FORMAT = "optitac-edge-shapes"
#: Version 2: subsets index the 8-vector ``[log-Hu x 7, q4]`` (``n_inputs`` and
#: ``q4_floor`` in the meta). Version-1 bundles load as 7-input (log-Hu only) models.
SHAPE_MODEL_VERSION = 2
#: Model kinds: the paper's unsupervised GMM, and one mixture per class.
KINDS = ("gmm_unsupervised", "gmm_per_class")
_ARRAYS = ("subset", "mean", "std", "weights", "means", "precisions_cholesky", "component_class")


def _frozen(a: Any, dtype: type, ndim: int, name: str) -> np.ndarray:
    arr: np.ndarray = np.array(a, dtype=dtype, copy=True, order="C")
    if arr.ndim != ndim:
        raise ValueError(f"ShapeModel.{name} must have {ndim} dimensions, has shape {arr.shape}")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class ShapeModel:
    """A fitted shape classifier (numeric parameters only; no scikit-learn needed).

    Attributes
    ----------
    kind : str
        ``"gmm_unsupervised"`` (the paper's) or ``"gmm_per_class"``.
    class_names : tuple of str
        ``C`` class names, e.g. ``SHAPES``.
    subset : ndarray, shape (d,), int64
        0-based indices into the input vector ``[L1 .. L7, q4]`` of the
        features used (e.g. ``[0, 1, 2]`` = M1M2M3, ``[0, 1, 7]`` = M1M2Q4).
    mean, std : ndarray, shape (d,), float64
        Standardisation of the selected features: ``z = (f - mean) / std``
        (``f`` from :func:`~optitac_edge.core.shapes.features.shape_features`).
    weights : ndarray, shape (K,), float64
        Component weights, summing to 1.
    means : ndarray, shape (K, d), float64
        Component means, standardised units.
    precisions_cholesky : ndarray, shape (K, d, d), float64
        Upper-triangular ``P_k`` with ``P_k P_k^T`` = component precision (as
        scikit-learn's ``precisions_cholesky_``): Mahalanobis distance
        ``|(z - mu_k) @ P_k|^2``.
    component_class : ndarray, shape (K,), int64
        Class index of each component, in ``[0, C)``.
    log_hu_cap : float
        The feature transform's cap ``C`` (``|h|`` floored at ``10**-C``).
    n_inputs : int
        Width of the input vector the model accepts: 8 (``ContactEstimate.features``)
        or 7 (``ContactEstimate.hu``, models without q4). Other widths are refused.
    q4_floor : float
        The q4 transform's floor (:func:`~optitac_edge.core.shapes.features.q4_log`).
    """

    kind: str
    class_names: tuple[str, ...]
    subset: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    weights: np.ndarray
    means: np.ndarray
    precisions_cholesky: np.ndarray
    component_class: np.ndarray
    log_hu_cap: float = LOG_HU_CAP
    n_inputs: int = N_FEATURES
    q4_floor: float = Q4_FLOOR

    def __post_init__(self) -> None:
        s = object.__setattr__
        s(self, "class_names", tuple(str(c) for c in self.class_names))
        s(self, "subset", _frozen(self.subset, np.int64, 1, "subset"))
        for name in ("mean", "std", "weights"):
            s(self, name, _frozen(getattr(self, name), np.float64, 1, name))
        s(self, "means", _frozen(self.means, np.float64, 2, "means"))
        s(self, "precisions_cholesky", _frozen(self.precisions_cholesky, np.float64, 3,
                                               "precisions_cholesky"))
        s(self, "component_class", _frozen(self.component_class, np.int64, 1, "component_class"))
        s(self, "log_hu_cap", float(self.log_hu_cap))
        s(self, "n_inputs", int(self.n_inputs))
        s(self, "q4_floor", float(self.q4_floor))
        d, k, c = self.subset.size, self.weights.size, len(self.class_names)
        if self.kind not in KINDS:
            raise ValueError(f"unknown shape model kind {self.kind!r}")
        if self.n_inputs not in (N_HU, N_FEATURES) or not self.q4_floor > 0:
            raise ValueError(f"n_inputs must be 7 or 8 (got {self.n_inputs}) and q4_floor > 0")
        in_range = np.all((self.subset >= 0) & (self.subset < self.n_inputs))
        if d == 0 or len(set(self.subset.tolist())) != d or not in_range:
            raise ValueError(f"bad feature subset {self.subset.tolist()} "
                             f"for {self.n_inputs} inputs")
        if self.mean.shape != (d,) or self.std.shape != (d,) or not np.all(self.std > 0):
            raise ValueError("mean/std must have shape (d,) and std > 0")
        if self.means.shape != (k, d) or self.precisions_cholesky.shape != (k, d, d):
            raise ValueError(f"means {self.means.shape} / precisions_cholesky "
                             f"{self.precisions_cholesky.shape} do not match K={k}, d={d}")
        if self.component_class.shape != (k,) or c == 0 or len(set(self.class_names)) != c:
            raise ValueError("component_class must have shape (K,) and class names be unique")
        if not np.all((self.component_class >= 0) & (self.component_class < c)):
            raise ValueError("component_class out of range")
        if not (np.all(self.weights > 0) and abs(self.weights.sum() - 1.0) < 1e-9):
            raise ValueError("weights must be positive and sum to 1")
        if not all(np.all(np.isfinite(a)) for a in (self.mean, self.std, self.means)) or not (
                np.isfinite(self.log_hu_cap) and np.isfinite(self.q4_floor)):
            raise ValueError("shape model parameters must be finite")
        diag = np.diagonal(self.precisions_cholesky, axis1=1, axis2=2)
        if not (np.all(np.isfinite(self.precisions_cholesky)) and np.all(diag > 0)):
            raise ValueError("precision Cholesky factors must be finite with positive diagonal")

    @property
    def n_features(self) -> int:
        """d, the number of features used."""
        return int(self.subset.size)

    @property
    def n_components(self) -> int:
        """K."""
        return int(self.weights.size)

    @property
    def subset_name(self) -> str:
        """E.g. ``"M1M2M3"`` or ``"M1M2Q4"`` (1-based Hu indices, Q4 for q4)."""
        return subset_name(self.subset)

    def to_bundle(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """JSON-able parameters and numeric arrays for a calibration bundle.

        Returns
        -------
        meta : dict
            ``format``, ``version``, ``kind``, ``class_names``, ``subset_name``,
            ``log_hu_cap``, ``n_inputs``, ``q4_floor``. The lead stores it as ``extra_meta["shapes"]``.
        arrays : dict of str to ndarray
            ``subset`` (d,) int64, ``mean``/``std`` (d,), ``weights`` (K,),
            ``means`` (K, d), ``precisions_cholesky`` (K, d, d) float64,
            ``component_class`` (K,) int64; stored as ``extra_arrays["shapes/<name>"]``.
        """
        meta = {
            "format": SHAPE_MODEL_FORMAT, "version": SHAPE_MODEL_VERSION, "kind": self.kind,
            "class_names": list(self.class_names), "subset_name": self.subset_name,
            "log_hu_cap": self.log_hu_cap, "n_inputs": self.n_inputs, "q4_floor": self.q4_floor,
        }
        return meta, {name: np.array(getattr(self, name)) for name in _ARRAYS}

    @classmethod
    def from_bundle(cls, meta: Mapping[str, Any], arrays: Mapping[str, np.ndarray]) -> ShapeModel:
        """Inverse of :meth:`to_bundle`.

        Raises
        ------
        ValueError
            If the format or version (1 or 2) is not this one's, or arrays are
            missing or inconsistent. A version-1 model (log-Hu only) has ``n_inputs == 7``.
        """
        version = meta.get("version")
        if meta.get("format") != SHAPE_MODEL_FORMAT or version not in (1, SHAPE_MODEL_VERSION):
            raise ValueError(f"not a version-1/{SHAPE_MODEL_VERSION} shape model: "
                             f"{meta.get('format')!r} v{version!r}")
        missing = [n for n in _ARRAYS if n not in arrays]
        if missing:
            raise ValueError(f"shape model arrays missing: {missing}")
        return cls(kind=str(meta["kind"]), class_names=tuple(meta["class_names"]),
                   log_hu_cap=float(meta["log_hu_cap"]),
                   n_inputs=N_HU if version == 1 else int(meta["n_inputs"]),
                   q4_floor=Q4_FLOOR if version == 1 else float(meta["q4_floor"]),
                   **{n: arrays[n] for n in _ARRAYS})

    def to_calibration_extras(
        self, key: str = "shapes"
    ) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        """``({key: meta}, {f"{key}/{name}": array})`` to merge into a bundle's extras."""
        meta, arrays = self.to_bundle()
        return {key: meta}, {f"{key}/{n}": a for n, a in arrays.items()}

    @classmethod
    def from_calibration_extras(
        cls, extra_meta: Mapping[str, Any], extra_arrays: Mapping[str, np.ndarray],
        key: str = "shapes",
    ) -> ShapeModel | None:
        """The model stored by :meth:`to_calibration_extras`, or None if the bundle has none."""
        if key not in extra_meta:
            return None
        prefix = f"{key}/"
        arrays = {n[len(prefix):]: a for n, a in extra_arrays.items() if n.startswith(prefix)}
        return cls.from_bundle(extra_meta[key], arrays)


def subset_name(subset: np.ndarray | tuple[int, ...]) -> str:
    """``"M1M2M3"`` for 0-based indices ``(0, 1, 2)``, ``"M1-M7"`` for all seven Hu
    invariants, ``Q4`` for index 7 (``"M1M2Q4"``, ``"M1-M7Q4"``)."""
    idx = [int(i) for i in subset]
    hu = [i for i in idx if i != Q4_INDEX]
    name = "M1-M7" if hu == list(range(N_HU)) else "".join(f"M{i + 1}" for i in hu)
    return name + ("Q4" if Q4_INDEX in idx else "")
