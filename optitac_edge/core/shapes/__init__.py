"""Contact-shape classification at run time (edge, circle, square, ellipse, triangle) from
log-Hu invariants and the 4-fold symmetry q4 (``ContactEstimate.features``, shape (8,)).

Runtime (numpy only)::

    model = ShapeModel.from_calibration_extras(bundle.extra_meta, bundle.extra_arrays)
    clf = ShapeClassifier(model)
    est.shape, est.confidence = clf.classify(est.features)  # ~10 us per frame

Modules: :mod:`.features` (the robust input transform), :mod:`.model` (the
closed-form model and its bundle form), :mod:`.evaluate` (numpy evaluation),
:mod:`.onnx_runtime` (the same with onnxruntime). Fitting and ONNX export are
offline: :mod:`optitac_edge.calibration.shape_fit`, :mod:`optitac_edge.calibration.onnx_export`.
"""

from optitac_edge.core.shapes.evaluate import CompiledShapeModel, ShapeClassifier, class_proba_numpy
from optitac_edge.core.shapes.features import LOG_HU_CAP, N_FEATURES, Q4_FLOOR, Q4_INDEX, shape_features
from optitac_edge.core.shapes.model import KINDS, ShapeModel, subset_name

__all__ = [
    "KINDS",
    "LOG_HU_CAP",
    "N_FEATURES",
    "Q4_FLOOR",
    "Q4_INDEX",
    "CompiledShapeModel",
    "ShapeClassifier",
    "ShapeModel",
    "class_proba_numpy",
    "shape_features",
    "subset_name",
]
