"""The shape classifier's two mixtures, fitted on standardised shape features (scikit-learn, offline).

* :func:`gmm_unsupervised` -- the paper's: one full-covariance Gaussian mixture with a component per
  class, clusters named by a Hungarian assignment on the training labels;
* :func:`gmm_per_class` -- supervised: a full-covariance mixture of 1..3 components per class (count
  by BIC), weighted by the class frequencies (the Bayes classifier).

Both return a :class:`~optitac_edge.core.shapes.model.ShapeModel`, the runtime's form of either.
:mod:`.shape_fit` chooses between them on held-out presses.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from optitac_edge.core.shapes.features import Q4_FLOOR
from optitac_edge.core.shapes.model import ShapeModel

#: Starts of a per-class mixture of more than one component (the best by likelihood is kept).
PER_CLASS_RESTARTS = 2


def _standardise(f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean = f.mean(axis=0)
    std = f.std(axis=0)
    return mean, np.where(std > 1e-12, std, 1.0)


def fit_unsupervised(
    f: np.ndarray, y: np.ndarray, class_names: tuple[str, ...], subset: tuple[int, ...], *,
    seed: int = 0, n_init: int = 5, reg_covar: float = 1e-6, q4_floor: float = Q4_FLOOR,
) -> ShapeModel:
    """The paper's GMM; see :func:`gmm_unsupervised` (this drops the estimator)."""
    return gmm_unsupervised(f, y, class_names, subset, seed=seed, n_init=n_init,
                            reg_covar=reg_covar, q4_floor=q4_floor)[0]


def gmm_unsupervised(
    f: np.ndarray, y: np.ndarray, class_names: tuple[str, ...], subset: tuple[int, ...], *,
    seed: int = 0, n_init: int = 5, reg_covar: float = 1e-6, q4_floor: float = Q4_FLOOR,
) -> tuple[ShapeModel, Any]:
    """The paper's GMM: ``C`` clusters on the standardised subset, mapped to classes.

    Parameters
    ----------
    f : ndarray, shape (n, W), float64
        Transformed features (:func:`shape_features`), W = 8 (with q4) or 7;
        the model's ``n_inputs`` is W.
    y : ndarray, shape (n,), int
        Class indices into ``class_names`` (used only to name the clusters).
    class_names : tuple of str
    subset : tuple of int
    seed, n_init, reg_covar
        scikit-learn ``GaussianMixture`` settings (``reg_covar`` in standardised units).
    q4_floor : float
        The q4 floor ``f`` was transformed with (stored in the model).

    Returns
    -------
    model : ShapeModel
    estimator : sklearn.mixture.GaussianMixture
        Fitted on ``(f[:, subset] - model.mean) / model.std``; cluster ``k`` is
        class ``model.component_class[k]``.
    """
    from scipy.optimize import linear_sum_assignment
    from sklearn.mixture import GaussianMixture

    c = len(class_names)
    x = f[:, list(subset)]
    mean, std = _standardise(x)
    z = (x - mean) / std
    gm = GaussianMixture(n_components=c, covariance_type="full", n_init=n_init,
                         random_state=seed, reg_covar=reg_covar).fit(z)
    counts = np.zeros((c, c), dtype=np.int64)
    np.add.at(counts, (gm.predict(z), y), 1)
    rows, cols = linear_sum_assignment(-counts)
    mapping = np.empty(c, dtype=np.int64)
    mapping[rows] = cols
    model = ShapeModel(kind="gmm_unsupervised", class_names=class_names, subset=np.array(subset),
                       mean=mean, std=std, weights=gm.weights_, means=gm.means_,
                       precisions_cholesky=gm.precisions_cholesky_, component_class=mapping,
                       n_inputs=f.shape[1], q4_floor=q4_floor)
    return model, gm


def fit_supervised(
    f: np.ndarray, y: np.ndarray, class_names: tuple[str, ...], subset: tuple[int, ...], *,
    seed: int = 0, max_components: int = 3, reg_covar: float = 1e-4, q4_floor: float = Q4_FLOOR,
) -> ShapeModel:
    """The per-class mixture; see :func:`gmm_per_class` (this drops the estimators)."""
    return gmm_per_class(f, y, class_names, subset, seed=seed, max_components=max_components,
                         reg_covar=reg_covar, q4_floor=q4_floor)[0]


def gmm_per_class(
    f: np.ndarray, y: np.ndarray, class_names: tuple[str, ...], subset: tuple[int, ...], *,
    seed: int = 0, max_components: int = 3, reg_covar: float = 1e-4, q4_floor: float = Q4_FLOOR,
) -> tuple[ShapeModel, list[Any], np.ndarray]:
    """Supervised: a full-covariance mixture per class, class priors = class frequencies.

    Each class gets 1..``max_components`` components, the count chosen by BIC.

    Parameters as :func:`gmm_unsupervised`; every class needs >= 2 training
    frames, and gets k > 1 components only with at least ``k * (d + 2)`` frames.
    A k > 1 mixture is the best of :data:`PER_CLASS_RESTARTS` starts (k = 1 is deterministic).

    Returns
    -------
    model : ShapeModel
        The equivalent single mixture, components labelled with their class.
    estimators : list of sklearn.mixture.GaussianMixture
        One per class (on standardised features).
    priors : ndarray, shape (C,), float64
        Class frequencies in ``y``.
    """
    from sklearn.mixture import GaussianMixture

    x = f[:, list(subset)]
    d = x.shape[1]
    mean, std = _standardise(x)
    z = (x - mean) / std
    weights, means, precs, comp_class, ests, priors = [], [], [], [], [], []
    for ci, name in enumerate(class_names):
        zc = z[y == ci]
        if zc.shape[0] < 2:
            raise ValueError(f"class {name!r} has {zc.shape[0]} training frames; need >= 2")
        best: Any = None
        best_bic = np.inf
        for k in range(1, max_components + 1):
            if k > 1 and zc.shape[0] < k * (d + 2):
                break
            gm = GaussianMixture(n_components=k, covariance_type="full",
                                 n_init=PER_CLASS_RESTARTS if k > 1 else 1,
                                 random_state=seed, reg_covar=reg_covar).fit(zc)
            bic = gm.bic(zc)
            if bic < best_bic:
                best, best_bic = gm, bic
        prior = zc.shape[0] / z.shape[0]
        ests.append(best)
        priors.append(prior)
        weights.append(prior * best.weights_)
        means.append(best.means_)
        precs.append(best.precisions_cholesky_)
        comp_class.append(np.full(best.n_components, ci))
    w = np.concatenate(weights)
    model = ShapeModel(kind="gmm_per_class", class_names=class_names, subset=np.array(subset),
                       mean=mean, std=std, weights=w / w.sum(), means=np.concatenate(means),
                       precisions_cholesky=np.concatenate(precs),
                       component_class=np.concatenate(comp_class), n_inputs=f.shape[1],
                       q4_floor=q4_floor)
    return model, ests, np.array(priors)
