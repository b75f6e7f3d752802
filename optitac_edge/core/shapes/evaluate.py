"""Runtime shape classification: numpy only, no scikit-learn.

For a feature vector ``z`` (standardised, see :class:`~optitac_edge.core.shapes.model.ShapeModel`)
component ``k`` has log-density ``log w_k + sum(log diag P_k) - d/2 log(2 pi)
- |(z - mu_k) P_k|^2 / 2``; the component posteriors are a softmax of these
and a class's probability is the sum over its components. The arithmetic is
laid out as a few matrix products with precomputed constants
(:class:`CompiledShapeModel`), shared with the ONNX export so both compute the
same thing in the same order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from optitac_edge.core.shapes.features import Q4_INDEX, Q4_MAX, SIGNED, ZERO_IS_NULL, shape_features
from optitac_edge.core.shapes.model import ShapeModel


@dataclass(frozen=True, eq=False)
class CompiledShapeModel:
    """Precomputed constants of a :class:`ShapeModel` (d features, K components, C classes).

    Attributes
    ----------
    subset : ndarray, shape (d,), int64
    mean, std : ndarray, shape (d,), float64
    proj : ndarray, shape (d, K*d), float64
        ``[P_1 | P_2 | ... | P_K]``: ``z @ proj`` stacks ``z @ P_k``.
    offset : ndarray, shape (K*d,), float64
        ``[mu_1 P_1 | ... | mu_K P_K]``.
    block_sum : ndarray, shape (K*d, K), float64
        Sums each block of d squared terms: Mahalanobis distances.
    const : ndarray, shape (K,), float64
        ``log w_k + sum(log diag P_k) - d/2 log(2 pi)``.
    class_map : ndarray, shape (K, C), float64
        One-hot component -> class.
    """

    subset: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    proj: np.ndarray
    offset: np.ndarray
    block_sum: np.ndarray
    const: np.ndarray
    class_map: np.ndarray

    @classmethod
    def from_model(cls, model: ShapeModel) -> CompiledShapeModel:
        """Precompute the constants."""
        d, k, c = model.n_features, model.n_components, len(model.class_names)
        prec = model.precisions_cholesky
        proj = np.ascontiguousarray(prec.transpose(1, 0, 2).reshape(d, k * d))
        offset = np.einsum("kd,kdj->kj", model.means, prec).reshape(k * d)
        block_sum = np.kron(np.eye(k), np.ones((d, 1)))
        logdet = np.log(np.diagonal(prec, axis1=1, axis2=2)).sum(axis=1)
        const = np.log(model.weights) + logdet - 0.5 * d * math.log(2.0 * math.pi)
        class_map = np.zeros((k, c))
        class_map[np.arange(k), model.component_class] = 1.0
        return cls(np.array(model.subset), np.array(model.mean), np.array(model.std), proj,
                   np.ascontiguousarray(offset), np.ascontiguousarray(block_sum), const, class_map)


def class_proba_numpy(compiled: CompiledShapeModel, features: np.ndarray) -> np.ndarray:
    """Class probabilities from transformed features (vectorised reference form).

    Parameters
    ----------
    compiled : CompiledShapeModel
    features : ndarray, shape (n, 8) or (n, 7), float64
        Output of :func:`~optitac_edge.core.shapes.features.shape_features` (the
        model's input width).

    Returns
    -------
    ndarray, shape (n, C), float64
        Rows sum to 1; all-NaN rows where a used feature is NaN.
    """
    z = (features[:, compiled.subset] - compiled.mean) / compiled.std
    y = z @ compiled.proj - compiled.offset
    ll = ((y * y) @ compiled.block_sum) * -0.5 + compiled.const
    with np.errstate(invalid="ignore"):
        e = np.exp(ll - ll.max(axis=1, keepdims=True))
        return (e @ compiled.class_map) / e.sum(axis=1, keepdims=True)


class ShapeClassifier:
    """Numpy shape classifier for the runtime pipeline.

    Parameters
    ----------
    model : ShapeModel

    Attributes
    ----------
    n_inputs : int
        Width of the feature vector accepted: 8 (``ContactEstimate.features``) or 7
        (``ContactEstimate.hu``, log-Hu-only models); others raise ValueError.

    Notes
    -----
    :meth:`classify` reuses preallocated buffers (not thread-safe: one
    classifier per pipeline thread) and allocates nothing per call beyond a
    few Python floats. It folds constants differently from
    :meth:`predict_proba` (offset into the projection, -1/2 into the block
    sums), so the two agree to rounding (~1e-16), not bit for bit.
    """

    def __init__(self, model: ShapeModel) -> None:
        self.model = model
        self.class_names = model.class_names
        self._c = CompiledShapeModel.from_model(model)
        c = self._c
        d, k = model.n_features, model.n_components
        self.n_inputs = model.n_inputs
        self._sel = [int(i) for i in c.subset]
        self._rule = [(bool(SIGNED[i]), bool(ZERO_IS_NULL[i]), i == Q4_INDEX) for i in self._sel]
        self._q4_floor = model.q4_floor
        self._mean = [float(v) for v in c.mean]
        self._std = [float(v) for v in c.std]
        self._cap = model.log_hu_cap
        # classify(): offset folded into the projection (z gets a constant 1), -1/2 into the
        # block sums, and a ones column in the class map gives the normaliser.
        self._z = np.ones((1, d + 1))
        self._proj1 = np.ascontiguousarray(np.vstack([c.proj, -c.offset]))
        self._block1 = np.ascontiguousarray(c.block_sum * -0.5)
        self._map1 = np.ascontiguousarray(np.hstack([c.class_map, np.ones((k, 1))]))
        self._y = np.empty((1, k * d))
        self._ll = np.empty((1, k))
        self._top = np.zeros(())  # 0-d operand: a scalar given to a ufunc becomes a new array every call
        self._const = np.ascontiguousarray(np.asarray(c.const, dtype=np.float64).reshape(1, k))
        self._p = np.empty((1, len(model.class_names) + 1))
        self._n_cls = len(model.class_names)

    def kernel_arrays(self) -> dict[str, Any]:
        """What the compiled kernel reads (:mod:`optitac_edge.core.compiled`): the transform's rules and the
        constants :meth:`classify` uses, folded the same way."""
        rules = [int(signed) | 2 * int(zero_null) | 4 * int(q4) for signed, zero_null, q4 in self._rule]
        return {"shape_d": len(self._sel), "shape_k": int(self._const.shape[1]), "shape_c": self._n_cls,
                "shape_sel": np.array(self._sel, dtype=np.int32), "shape_rule": np.array(rules, dtype=np.int32),
                "shape_mean": np.array(self._mean), "shape_std": np.array(self._std), "shape_cap": float(self._cap),
                "shape_q4_floor": float(self._q4_floor), "shape_q4_max": float(Q4_MAX),
                "shape_proj1": self._proj1, "shape_const": self._const, "shape_map1": self._map1}

    def predict_proba(self, features: np.ndarray) -> np.ndarray:
        """Class probabilities of many contacts.

        Parameters
        ----------
        features : array_like, shape (n, W) or (W,), float
            ``W = model.n_inputs``: 8 for ``ContactEstimate.features``
            (``[log-Hu x 7, q4]``), 7 for a log-Hu-only model (``ContactEstimate.hu``).

        Returns
        -------
        ndarray, shape (n, C), float64
            Columns in ``model.class_names`` order; NaN rows where a used
            feature is NaN (no contact).

        Raises
        ------
        ValueError
            If the width is not ``model.n_inputs``.
        """
        L = np.asarray(features, dtype=np.float64)
        if L.ndim == 1:
            L = L[None, :]
        if L.ndim != 2 or L.shape[1] != self.n_inputs:
            raise width_error(np.shape(features), self.n_inputs)
        return class_proba_numpy(self._c, shape_features(L, self._cap, self._q4_floor))

    def predict(self, features: np.ndarray) -> np.ndarray:
        """Class names, shape (n,), str ('' where the probabilities are NaN)."""
        p = self.predict_proba(features)
        ok = np.isfinite(p).all(axis=1)
        names = np.array(self.class_names)[np.argmax(np.where(ok[:, None], p, 0.0), axis=1)]
        return np.where(ok, names, "")

    def classify(self, features: np.ndarray) -> tuple[str, float]:
        """Shape and confidence of one contact (the per-frame form).

        Parameters
        ----------
        features : ndarray, shape (W,), float64
            ``ContactEstimate.features`` (``W = model.n_inputs`` = 8), or
            ``ContactEstimate.hu`` for a log-Hu-only model (``W`` = 7).

        Returns
        -------
        shape : str
            The most probable class name; '' if a used feature is NaN.
        confidence : float
            Its posterior probability in [0, 1]; NaN with shape ''.

        Raises
        ------
        ValueError
            If ``len(features) != model.n_inputs``.
        """
        if len(features) != self.n_inputs:
            raise width_error(np.shape(features), self.n_inputs)
        cap, z = self._cap, self._z[0]
        for j, i in enumerate(self._sel):
            x = float(features[i])
            signed, zero_null, is_q4 = self._rule[j]
            if math.isnan(x):
                return "", math.nan
            if is_q4:
                f = math.log(min(max(x, 0.0), Q4_MAX) + self._q4_floor)
            elif signed:
                a = abs(x)
                f = 0.0 if a >= cap else (cap - a if x > 0 else (a - cap if x < 0 else 0.0))
            elif x == 0.0 and zero_null:
                f = cap
            else:
                f = min(max(x, -cap), cap)
            z[j] = (f - self._mean[j]) / self._std[j]
        y, ll, p = self._y, self._ll, self._p
        np.matmul(self._z, self._proj1, out=y)
        np.multiply(y, y, out=y)
        np.matmul(y, self._block1, out=ll)
        np.add(ll, self._const, out=ll)
        self._top.fill(max(ll[0].tolist()))
        np.subtract(ll, self._top, out=ll)
        np.exp(ll, out=ll)
        np.matmul(ll, self._map1, out=p)
        vals = p[0].tolist()
        best = max(range(self._n_cls), key=vals.__getitem__)
        return self.class_names[best], vals[best] / vals[-1]


def width_error(shape: tuple[int, ...], n_inputs: int) -> ValueError:
    """The error for a feature array of the wrong shape given to an ``n_inputs``-wide model."""
    what = ("ContactEstimate.features: [log-Hu x 7, q4]" if n_inputs == 8
            else "ContactEstimate.hu: log-Hu only (a model fitted without q4)")
    return ValueError(f"this shape model takes {n_inputs} features per contact ({what}), "
                     f"got an array of shape {shape}")
