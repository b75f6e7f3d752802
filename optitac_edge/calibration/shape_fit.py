"""Offline fitting of the shape classifier (needs scikit-learn, the ``[calibrate]`` extra).

Protocol (:func:`fit_shape_model`)
----------------------------------
1. Input: the pipeline's shape features ``[log-Hu x 7, q4]`` (n, 8), or the
   log-Hu invariants alone (n, 7). Rows with a NaN are dropped; the models see
   :func:`~optitac_edge.core.shapes.features.shape_features` of them.
2. **Held-out split**, stratified by class and grouped by press (``groups``:
   frames of one press are never on both sides): about ``holdout`` of each
   class's presses are held out. They are used only to report metrics.
3. Two model kinds, each searched over the paper's Hu subsets
   :data:`PAPER_SUBSETS` (M1M2, M1M3, M1M2M3 ... M1M2M7, M1-M7) and, with an
   8-wide input, the subsets with the 4-fold symmetry :data:`Q4_SUBSETS`
   (M1M2Q4, M1M3Q4, M1M2M3Q4, M1-M7Q4); features standardised with the training
   mean/std:

   * ``gmm_unsupervised`` -- the paper's: one 5-component full-covariance
     Gaussian mixture (``n_init`` restarts), clusters mapped to classes by a
     Hungarian assignment on the training labels;
   * ``gmm_per_class`` -- supervised: a full-covariance mixture of 1..3
     components per class (count by BIC on the class's training frames),
     weighted by the class frequencies: the Bayes classifier.

   The subset of each kind, and then the kind, is **selected on the training
   presses only**, by the mean average-diagonal (balanced accuracy) over
   ``cv_folds`` grouped, stratified folds (ties -> the simpler subset, then the
   paper's kind). The held-out metrics of every subset and both kinds are
   reported (the paper's table), but do not drive the choice, so the reported
   held-out figure of the chosen model is unbiased.
4. With ``refit=True`` (default) the chosen configuration is refitted on all
   frames for deployment (more presses per class; its metrics are those of
   the train-only fit, reported under ``holdout``; its resubstitution accuracy
   is given only as a sanity check). ``refit=False`` deploys the train-only fit.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from optitac_edge.calibration.folds import stratified_group_folds, stratified_group_split
from optitac_edge.calibration.shape_mixtures import fit_supervised, fit_unsupervised
from optitac_edge.core.shapes.evaluate import ShapeClassifier
from optitac_edge.core.shapes.features import N_FEATURES, N_HU, Q4_FLOOR, Q4_INDEX, shape_features
from optitac_edge.core.shapes.model import ShapeModel, subset_name

logger = logging.getLogger(__name__)

#: The paper's 8 Hu subsets (0-based): M1M2, M1M3, M1M2M3, M1M2M4 .. M1M2M7, M1-M7.
PAPER_SUBSETS: tuple[tuple[int, ...], ...] = (
    (0, 1), (0, 2), (0, 1, 2), (0, 1, 3), (0, 1, 4), (0, 1, 5), (0, 1, 6), tuple(range(N_HU)),
)
#: Extensions with the 4-fold symmetry q4 (index 7): M1M2Q4, M1M3Q4, M1M2M3Q4, M1-M7Q4.
Q4_SUBSETS: tuple[tuple[int, ...], ...] = (
    (0, 1, Q4_INDEX), (0, 2, Q4_INDEX), (0, 1, 2, Q4_INDEX), tuple(range(N_FEATURES)),
)
#: Searched by default with an 8-wide input (with a 7-wide one: :data:`PAPER_SUBSETS`).
ALL_SUBSETS = PAPER_SUBSETS + Q4_SUBSETS
#: The paper's best subset, M1M2M3: used when the selection cannot be cross-validated.
DEFAULT_SUBSET: tuple[int, ...] = (0, 1, 2)


@dataclass(frozen=True)
class ShapeMetrics:
    """Classification metrics on a set of frames.

    Attributes
    ----------
    confusion : ndarray, shape (C, C), int64
        ``confusion[true, predicted]`` counts.
    average_diagonal : float
        Mean over classes present of the row-normalised diagonal (balanced accuracy).
    accuracy : float
    f1 : dict of str to float
        Per-class F1 (NaN for a class neither present nor predicted).
    n : int
        Frames evaluated.
    """

    confusion: np.ndarray
    average_diagonal: float
    accuracy: float
    f1: dict[str, float]
    n: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-able (NaN -> None)."""
        def f(v: float) -> float | None:
            return None if not np.isfinite(v) else float(v)
        return {"average_diagonal": f(self.average_diagonal), "accuracy": f(self.accuracy),
                "f1": {k: f(v) for k, v in self.f1.items()}, "n": self.n,
                "confusion": self.confusion.tolist()}


@dataclass(frozen=True)
class SubsetResult:
    """One feature subset of one model kind: CV score on training presses, held-out metrics."""

    subset: tuple[int, ...]
    cv_average_diagonal: float
    holdout: ShapeMetrics

    @property
    def name(self) -> str:
        return subset_name(self.subset)


@dataclass(frozen=True)
class KindReport:
    """The subset search of one model kind.

    Attributes
    ----------
    kind : str
    subsets : list of SubsetResult
        In search order (:data:`PAPER_SUBSETS` then :data:`Q4_SUBSETS` by default).
    selected : tuple of int
        Chosen by CV on the training presses.
    holdout : ShapeMetrics
        Held-out metrics of the selected subset (fitted on the training presses).
    holdout_model : ShapeModel
        That train-only fit.
    """

    kind: str
    subsets: list[SubsetResult]
    selected: tuple[int, ...]
    holdout: ShapeMetrics
    holdout_model: ShapeModel

    @property
    def cv_score(self) -> float:
        return next(r.cv_average_diagonal for r in self.subsets if r.subset == self.selected)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind, "selected": subset_name(self.selected),
            "cv_average_diagonal": self.cv_score, "holdout": self.holdout.to_dict(),
            "subsets": {r.name: {"cv_average_diagonal": r.cv_average_diagonal,
                                 "holdout": r.holdout.to_dict()} for r in self.subsets},
        }


@dataclass(frozen=True)
class ShapeFitReport:
    """Result of :func:`fit_shape_model`.

    Attributes
    ----------
    model : ShapeModel
        The deployed model (refitted on all frames if ``refit``).
    kind : str
        The chosen kind.
    unsupervised, supervised : KindReport
        The paper's GMM and the per-class mixture.
    class_names : tuple of str
    train_index, test_index : ndarray, int64
        Rows (of the input) used for training / held out; disjoint.
    refit : bool
    resubstitution_accuracy : float
        Accuracy of ``model`` on all frames it was fitted on (sanity check only).
    n_dropped : int
        Input rows dropped for NaN features.
    """

    model: ShapeModel
    kind: str
    unsupervised: KindReport
    supervised: KindReport
    class_names: tuple[str, ...]
    train_index: np.ndarray
    test_index: np.ndarray
    refit: bool
    resubstitution_accuracy: float
    n_dropped: int = 0
    settings: dict[str, Any] = field(default_factory=dict)

    @property
    def chosen(self) -> KindReport:
        return self.unsupervised if self.kind == self.unsupervised.kind else self.supervised

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary (for a bundle's report)."""
        return {
            "kind": self.kind, "subset": self.model.subset_name,
            "n_inputs": self.model.n_inputs,
            "holdout_average_diagonal": self.chosen.holdout.average_diagonal,
            "holdout_accuracy": self.chosen.holdout.accuracy,
            "class_names": list(self.class_names), "n_train": int(self.train_index.size),
            "n_test": int(self.test_index.size), "n_dropped": self.n_dropped,
            "refit": self.refit, "resubstitution_accuracy": self.resubstitution_accuracy,
            "settings": self.settings,
            "unsupervised": self.unsupervised.to_dict(), "supervised": self.supervised.to_dict(),
        }


def evaluate_model(model: ShapeModel, features: np.ndarray, y: np.ndarray) -> ShapeMetrics:
    """Metrics of ``model`` (numpy runtime evaluator) on labelled frames.

    Parameters
    ----------
    model : ShapeModel
    features : ndarray, shape (n, model.n_inputs), float64
        Untransformed shape features (``ContactEstimate.features``, or ``.hu``
        for a 7-input model).
    y : ndarray, shape (n,), int
        True class indices.
    """
    c = len(model.class_names)
    p = ShapeClassifier(model).predict_proba(features)
    pred = np.argmax(np.nan_to_num(p, nan=-1.0), axis=1)
    conf = np.zeros((c, c), dtype=np.int64)
    np.add.at(conf, (y, pred), 1)
    support, predicted, tp = conf.sum(axis=1), conf.sum(axis=0), np.diag(conf)
    present = support > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        recall = tp / support
        f1 = 2.0 * tp / (support + predicted)
    n = int(y.size)
    return ShapeMetrics(
        confusion=conf,
        average_diagonal=float(recall[present].mean()) if present.any() else float("nan"),
        accuracy=float(tp.sum() / n) if n else float("nan"),
        f1={name: float(v) for name, v in zip(model.class_names, f1)},
        n=n,
    )


@dataclass(frozen=True)
class ShapeFitSettings:
    """How :func:`fit_shape_model` splits, searches and fits.

    Attributes
    ----------
    seed : int
        Seeds the split, folds and mixture initialisation.
    holdout : float
        Fraction of each class's presses held out for the reported metrics.
    cv_folds : int
        Folds over the training presses for the subset / kind selection.
    subsets : tuple of tuple of int, optional
        Feature subsets searched (0-based indices into the input vector; 7 = q4).
        Default :data:`ALL_SUBSETS` for an 8-wide input, :data:`PAPER_SUBSETS` for 7.
    refit : bool
        Refit the chosen configuration on all frames for deployment.
    n_init : int
        Restarts of the unsupervised mixture.
    max_components : int
        Components per class of the supervised mixture (chosen by BIC).
    reg_covar_unsupervised, reg_covar_supervised : float
        Covariance regularisation, standardised units.
    class_names : tuple of str, optional
        Class order; default the sorted unique labels.
    q4_floor : float
        The q4 transform's floor (:func:`~optitac_edge.core.shapes.features.q4_log`), kept in the model.
    """

    seed: int = 0
    holdout: float = 0.3
    cv_folds: int = 3
    subsets: tuple[tuple[int, ...], ...] | None = None
    refit: bool = True
    n_init: int = 5
    max_components: int = 3
    reg_covar_unsupervised: float = 1e-6
    reg_covar_supervised: float = 1e-4
    class_names: tuple[str, ...] | None = None
    q4_floor: float = Q4_FLOOR

    def to_json(self, subsets: tuple[tuple[int, ...], ...], model: ShapeModel) -> dict[str, Any]:
        """The settings a report keeps (the subsets searched, the model's caps)."""
        return {"seed": self.seed, "holdout": self.holdout, "cv_folds": self.cv_folds, "n_init": self.n_init,
                "max_components": self.max_components, "log_hu_cap": model.log_hu_cap,
                "q4_floor": model.q4_floor, "subsets": [subset_name(s) for s in subsets],
                "reg_covar_unsupervised": self.reg_covar_unsupervised,
                "reg_covar_supervised": self.reg_covar_supervised}


_DEFAULTS = ShapeFitSettings()


def _fit_kind(kind: str, f: np.ndarray, y: np.ndarray, names: tuple[str, ...],
              subset: tuple[int, ...], s: ShapeFitSettings) -> ShapeModel:
    if kind == "gmm_unsupervised":
        return fit_unsupervised(f, y, names, subset, seed=s.seed, n_init=s.n_init,
                                reg_covar=s.reg_covar_unsupervised, q4_floor=s.q4_floor)
    return fit_supervised(f, y, names, subset, seed=s.seed, max_components=s.max_components,
                          reg_covar=s.reg_covar_supervised, q4_floor=s.q4_floor)


def fit_shape_model(features: np.ndarray, labels: np.ndarray, groups: np.ndarray | None = None,
                    settings: ShapeFitSettings = _DEFAULTS) -> ShapeFitReport:
    """Fit and evaluate both shape classifiers; keep the better (see the module docstring).

    Parameters
    ----------
    features : ndarray, shape (n, 8) or (n, 7), float64
        Shape features of contact frames: ``ContactEstimate.features``
        (``[log-Hu x 7, q4]``), or ``ContactEstimate.hu`` (log-Hu only: the
        q4 subsets are then not searched). The deployed model takes the same width.
    labels : ndarray, shape (n,), str
        True shape per frame.
    groups : ndarray, shape (n,), optional
        Press id per frame (frames of a press stay together); default: each frame its own.
    settings : ShapeFitSettings
        Split, search and mixture settings.

    Returns
    -------
    ShapeFitReport
    """
    from threadpoolctl import threadpool_limits  # a scikit-learn dependency

    # Tiny problems: thread start-up dominates (about 20x slower with threads).
    with threadpool_limits(limits=1):
        return _fit_shape_model(_Frames.of(features, labels, groups, settings), settings)


@dataclass(frozen=True)
class _Frames:
    """The labelled frames a fit uses (rows with a NaN feature dropped), and the subsets it searches."""

    x: np.ndarray  # (n, W) the untransformed features
    f: np.ndarray  # (n, W) shape_features(x)
    y: np.ndarray  # (n,) class indices into names
    groups: np.ndarray  # (n,) press ids
    rows: np.ndarray  # (n,) the input rows kept
    names: tuple[str, ...]
    subsets: tuple[tuple[int, ...], ...]
    n_dropped: int

    @classmethod
    def of(cls, features: np.ndarray, labels: np.ndarray, groups: np.ndarray | None,
           s: ShapeFitSettings) -> _Frames:
        x = np.asarray(features, dtype=np.float64)
        labels = np.asarray(labels).astype(str)
        if x.ndim != 2 or x.shape[1] not in (N_HU, N_FEATURES) or labels.shape != (x.shape[0],):
            raise ValueError(f"need features (n, 8) [log-Hu x 7, q4] or (n, 7) [log-Hu] and "
                             f"labels (n,), got {x.shape} and {labels.shape}")
        subsets = s.subsets
        if subsets is None:
            subsets = ALL_SUBSETS if x.shape[1] == N_FEATURES else PAPER_SUBSETS
        subsets = tuple(tuple(int(i) for i in sub) for sub in subsets)
        if any(i < 0 or i >= x.shape[1] for sub in subsets for i in sub):
            raise ValueError(f"subsets {[subset_name(sub) for sub in subsets]} need more than the "
                             f"{x.shape[1]} input features (Q4 needs the 8-wide ContactEstimate.features)")
        groups = np.arange(x.shape[0]) if groups is None else np.asarray(groups)
        keep = ~np.isnan(x).any(axis=1)
        n_dropped = int((~keep).sum())
        if n_dropped:
            logger.warning("shape fit: dropping %d frames with NaN features", n_dropped)
        x, labels, groups = x[keep], labels[keep], groups[keep]
        names = tuple(s.class_names) if s.class_names is not None else tuple(np.unique(labels).tolist())
        lookup = {n: i for i, n in enumerate(names)}
        if set(labels.tolist()) - set(names):
            raise ValueError(f"labels not in class_names: {sorted(set(labels.tolist()) - set(names))}")
        y = np.array([lookup[v] for v in labels], dtype=np.int64)
        return cls(x, shape_features(x, q4_floor=s.q4_floor), y, groups, np.flatnonzero(keep), names, subsets,
                   n_dropped)


def _search_kind(kind: str, d: _Frames, tr: np.ndarray, te: np.ndarray, folds: list[np.ndarray],
                 s: ShapeFitSettings) -> KindReport:
    """Every subset of one kind: its CV score on the training presses and its held-out metrics; the best."""
    x, f, y = d.x, d.f, d.y
    results, fits = [], {}
    for subset in d.subsets:
        scores = []
        for held in folds:
            fit_rows = tr[np.setdiff1d(np.arange(tr.size), held)]
            if held.size == 0 or np.bincount(y[fit_rows], minlength=len(d.names)).min() < 2:
                continue  # a class (nearly) absent from this fold's training presses
            m = _fit_kind(kind, f[fit_rows], y[fit_rows], d.names, subset, s)
            scores.append(evaluate_model(m, x[tr[held]], y[tr[held]]).average_diagonal)
        fits[subset] = _fit_kind(kind, f[tr], y[tr], d.names, subset, s)
        cv = float(np.mean(scores)) if scores else float("nan")
        results.append(SubsetResult(subset, cv, evaluate_model(fits[subset], x[te], y[te])))
        logger.info("shape fit %s %s: cv %.3f held-out %.3f", kind, results[-1].name,
                    results[-1].cv_average_diagonal, results[-1].holdout.average_diagonal)
    if all(np.isnan(r.cv_average_diagonal) for r in results):
        logger.warning("shape fit: too few presses per class for %d-fold selection; "
                       "using %s", s.cv_folds, subset_name(DEFAULT_SUBSET))
        best = next((r for r in results if r.subset == DEFAULT_SUBSET), results[0])
    else:
        best = max(results, key=lambda r: (np.nan_to_num(r.cv_average_diagonal, nan=-1.0), -len(r.subset)))
    return KindReport(kind, results, best.subset, best.holdout, fits[best.subset])


def _fit_shape_model(d: _Frames, s: ShapeFitSettings) -> ShapeFitReport:
    rng = np.random.default_rng(s.seed)
    tr, te = stratified_group_split(d.y, d.groups, s.holdout, rng)
    folds = stratified_group_folds(d.y[tr], d.groups[tr], s.cv_folds, rng)
    unsup, sup = (_search_kind(kind, d, tr, te, folds, s) for kind in ("gmm_unsupervised", "gmm_per_class"))
    better = np.nan_to_num(sup.cv_score, nan=-1.0) > np.nan_to_num(unsup.cv_score, nan=-1.0)
    chosen = sup if better else unsup  # ties -> the paper's
    if s.refit:
        model = _fit_kind(chosen.kind, d.f, d.y, d.names, chosen.selected, s)
    else:
        model = chosen.holdout_model
    resub = evaluate_model(model, d.x, d.y) if s.refit else evaluate_model(model, d.x[tr], d.y[tr])
    logger.info("shape fit: chose %s %s (held-out average diagonal %.3f)", chosen.kind,
                subset_name(chosen.selected), chosen.holdout.average_diagonal)
    return ShapeFitReport(
        model=model, kind=chosen.kind, unsupervised=unsup, supervised=sup, class_names=d.names,
        train_index=d.rows[tr], test_index=d.rows[te], refit=s.refit,
        resubstitution_accuracy=resub.accuracy, n_dropped=d.n_dropped, settings=s.to_json(d.subsets, model),
    )
