"""ONNX form of a :class:`~optitac_edge.core.shapes.model.ShapeModel` (needs ``onnx`` to export,
``onnxruntime`` to run: the ``[calibrate]`` / ``[onnx]`` extras).

The graph takes ``features`` (n, W) float64 -- the pipeline's shape features
``[log-Hu x 7, q4]`` (W = 8, ``ContactEstimate.features``) or log-Hu only
(W = 7, a model fitted without q4), untransformed -- and outputs
``probabilities`` (n, C) float64, doing the
feature transform (:func:`~optitac_edge.core.shapes.features.shape_features`), the
standardisation and the mixture posterior with the same constants and in the
same order as :func:`~optitac_edge.core.shapes.evaluate.class_proba_numpy`. The
class names are in the model's metadata (``class_names``, JSON), W in ``n_inputs``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from optitac_edge.core.shapes.evaluate import CompiledShapeModel
from optitac_edge.core.shapes.features import IS_Q4, Q4_MAX, SIGNED, ZERO_IS_NULL
from optitac_edge.core.shapes.model import ShapeModel
from optitac_edge.core.shapes.onnx_runtime import OUTPUT_NAME
from optitac_edge.errors import missing_extra
from optitac_edge.io.files import write_file_atomic

if TYPE_CHECKING:
    import onnx

#: ONNX opset of the exported graph (onnxruntime >= 1.14 runs it).
OPSET = 17
INPUT_NAME = "features"


def build_onnx(model: ShapeModel) -> onnx.ModelProto:
    """The ONNX model of ``model``; see the module docstring.

    Raises
    ------
    MissingExtraError
        If the ``onnx`` package is not installed.
    """
    try:
        import onnx
        from onnx import TensorProto, helper, numpy_helper
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise missing_extra("onnx", "ONNX export") from exc

    c = CompiledShapeModel.from_model(model)
    k, n_cls = model.n_components, len(model.class_names)
    cap, w = model.log_hu_cap, model.n_inputs
    consts = {
        "cap": np.array(cap), "neg_cap": np.array(-cap), "zero": np.array(0.0),
        "signed": SIGNED[:w].copy(), "zero_null": ZERO_IS_NULL[:w].copy(),
        "is_q4": IS_Q4[:w].copy(), "q4_max": np.array(Q4_MAX),
        "q4_floor": np.array(model.q4_floor),
        "subset": c.subset.astype(np.int64), "mean": c.mean, "std": c.std,
        "proj": c.proj, "offset": c.offset, "block_sum": c.block_sum,
        "neg_half": np.array(-0.5), "const": c.const, "class_map": c.class_map,
    }
    inits = [numpy_helper.from_array(np.asarray(v), name=n) for n, v in consts.items()]
    N = helper.make_node
    x = INPUT_NAME
    nodes = [
        # h1..h4: clip(L, -C, C) with NaN passing through; exact 0 of h2..h4 -> C
        N("Greater", [x, "cap"], ["gt"]),
        N("Less", [x, "neg_cap"], ["lt"]),
        N("Where", ["lt", "neg_cap", x], ["lo"]),
        N("Where", ["gt", "cap", "lo"], ["clipped"]),
        N("Equal", [x, "zero"], ["is0"]),
        N("And", ["is0", "zero_null"], ["null"]),
        N("Where", ["null", "cap", "clipped"], ["nonneg"]),
        # h5..h7: sign(L) * (C - |L|), 0 where |L| >= C
        N("Abs", [x], ["a"]),
        N("Sub", ["cap", "a"], ["rest"]),
        N("Sign", [x], ["sgn"]),
        N("Mul", ["sgn", "rest"], ["symlog"]),
        N("GreaterOrEqual", ["a", "cap"], ["far"]),
        N("Where", ["far", "zero", "symlog"], ["signed_f"]),
        N("Where", ["signed", "signed_f", "nonneg"], ["hu_f"]),
        # q4: ln(clip(q4, 0, Q4_MAX) + floor), NaN passing through (computed on every column)
        N("Greater", [x, "q4_max"], ["q_gt"]),
        N("Less", [x, "zero"], ["q_lt"]),
        N("Where", ["q_lt", "zero", x], ["q_lo"]),
        N("Where", ["q_gt", "q4_max", "q_lo"], ["q_clipped"]),
        N("Add", ["q_clipped", "q4_floor"], ["q_shifted"]),
        N("Log", ["q_shifted"], ["q4_f"]),
        N("Where", ["is_q4", "q4_f", "hu_f"], ["transformed"]),
        # standardised subset, Mahalanobis distances, log densities
        N("Gather", ["transformed", "subset"], ["sel"], axis=1),
        N("Sub", ["sel", "mean"], ["centred"]),
        N("Div", ["centred", "std"], ["z"]),
        N("MatMul", ["z", "proj"], ["zp"]),
        N("Sub", ["zp", "offset"], ["y"]),
        N("Mul", ["y", "y"], ["y2"]),
        N("MatMul", ["y2", "block_sum"], ["maha"]),
        N("Mul", ["maha", "neg_half"], ["half"]),
        N("Add", ["half", "const"], ["ll"]),
        # softmax over components, summed per class
        N("ReduceMax", ["ll"], ["llmax"], axes=[1], keepdims=1),
        N("Sub", ["ll", "llmax"], ["shifted"]),
        N("Exp", ["shifted"], ["e"]),
        N("MatMul", ["e", "class_map"], ["unnorm"]),
        N("ReduceSum", ["e", "axis1"], ["total"], keepdims=1),
        N("Div", ["unnorm", "total"], [OUTPUT_NAME]),
    ]
    inits.append(numpy_helper.from_array(np.array([1], dtype=np.int64), name="axis1"))
    graph = helper.make_graph(
        nodes, "optitac_edge_shapes",
        [helper.make_tensor_value_info(INPUT_NAME, TensorProto.DOUBLE, ["n", w])],
        [helper.make_tensor_value_info(OUTPUT_NAME, TensorProto.DOUBLE, ["n", n_cls])], inits,
    )
    onnx_model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                                   producer_name="optitac-edge")
    onnx_model.ir_version = min(onnx_model.ir_version, 8)
    meta, _ = model.to_bundle()
    for key, value in {"class_names": json.dumps(list(model.class_names)),
                       "shape_model": json.dumps(meta), "n_components": str(k),
                       "n_inputs": str(w)}.items():
        onnx_model.metadata_props.add(key=key, value=value)
    onnx.checker.check_model(onnx_model)
    return onnx_model


def export_onnx(model: ShapeModel, path: str | Path) -> Path:
    """Write the ONNX form of ``model`` to ``path``.

    Parameters
    ----------
    model : ShapeModel
    path : str or Path

    Returns
    -------
    Path
    """
    path = Path(path)
    write_file_atomic(path, build_onnx(model).SerializeToString())
    return path
