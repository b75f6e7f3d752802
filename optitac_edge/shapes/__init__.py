"""Contact-shape classification (edge, circle, square, ellipse, triangle) from log-Hu
invariants and the 4-fold symmetry q4 (``ContactEstimate.features``, shape (8,)).

Runtime (numpy only)::

    model = ShapeModel.from_calibration_extras(bundle.extra_meta, bundle.extra_arrays)
    clf = ShapeClassifier(model)
    est.shape, est.confidence = clf.classify(est.features)  # ~10 us per frame

Offline (scikit-learn, the ``[calibrate]`` extra)::

    report = fit_shape_model(features, labels, groups=press_ids)  # features (n, 8)
    meta, arrays = report.model.to_calibration_extras()   # -> extra_meta / extra_arrays

Modules: :mod:`.features` (the robust input transform), :mod:`.model` (the
closed-form model and its bundle form), :mod:`.evaluate` (numpy runtime),
:mod:`.fit` (offline fitting and held-out evaluation), :mod:`.onnx_export`
(ONNX graph and onnxruntime classifier), :mod:`.synthetic` (labelled
synthetic features for tests).
"""

from .evaluate import CompiledShapeModel, ShapeClassifier, class_proba_numpy
from .features import LOG_HU_CAP, N_FEATURES, Q4_FLOOR, Q4_INDEX, shape_features
from .fit import (
    ALL_SUBSETS,
    PAPER_SUBSETS,
    Q4_SUBSETS,
    ShapeFitReport,
    ShapeMetrics,
    evaluate_model,
    fit_shape_model,
)
from .model import KINDS, ShapeModel, subset_name
from .onnx_export import OnnxShapeClassifier, export_onnx

__all__ = [
    "ALL_SUBSETS",
    "KINDS",
    "LOG_HU_CAP",
    "N_FEATURES",
    "PAPER_SUBSETS",
    "Q4_FLOOR",
    "Q4_INDEX",
    "Q4_SUBSETS",
    "CompiledShapeModel",
    "OnnxShapeClassifier",
    "ShapeClassifier",
    "ShapeFitReport",
    "ShapeMetrics",
    "ShapeModel",
    "class_proba_numpy",
    "evaluate_model",
    "export_onnx",
    "fit_shape_model",
    "shape_features",
    "subset_name",
]
