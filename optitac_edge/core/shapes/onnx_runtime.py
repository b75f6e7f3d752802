"""Evaluate an exported shape model with onnxruntime (the ``[onnx]`` extra), per contact.

The graph is written by :func:`optitac_edge.calibration.onnx_export.export_onnx`;
this is the runtime side, with the :class:`~optitac_edge.core.shapes.evaluate.ShapeClassifier` API.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from optitac_edge.core.shapes.evaluate import width_error
from optitac_edge.errors import missing_extra

#: Name of the graph's output (see :mod:`optitac_edge.calibration.onnx_export`).
OUTPUT_NAME = "probabilities"


class OnnxShapeClassifier:
    """The :class:`~optitac_edge.core.shapes.evaluate.ShapeClassifier` API on onnxruntime.

    Parameters
    ----------
    path : str or Path
        A file written by :func:`optitac_edge.calibration.onnx_export.export_onnx`.
    threads : int
        onnxruntime intra-op threads (default 1: the model is tiny).

    Raises
    ------
    MissingExtraError
        If onnxruntime is not installed (the ``onnx`` extra).
    """

    def __init__(self, path: str | Path, threads: int = 1) -> None:
        try:
            import onnxruntime as ort
        except ImportError as exc:
            raise missing_extra("onnxruntime", "the onnx shape backend") from exc
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        self._session = ort.InferenceSession(str(path), sess_options=opts,
                                             providers=["CPUExecutionProvider"])
        props = self._session.get_modelmeta().custom_metadata_map
        self.class_names: tuple[str, ...] = tuple(json.loads(props["class_names"]))
        # the graph's input: "features" (n, W); "hu_log" (n, 7) in files written before q4
        inp = self._session.get_inputs()[0]
        self._input: str = inp.name
        #: Input width W: 8 (``ContactEstimate.features``) or 7 (log-Hu only).
        self.n_inputs = int(inp.shape[1])
        self._one = np.empty((1, self.n_inputs), dtype=np.float64)

    def predict_proba(self, features: np.ndarray) -> np.ndarray:
        """Class probabilities, shape (n, C), float64 (as :meth:`ShapeClassifier.predict_proba`).

        Parameters
        ----------
        features : array_like, shape (n, W) or (W,), float
            W = :attr:`n_inputs`; another width raises ValueError.
        """
        L = np.ascontiguousarray(features, dtype=np.float64)
        if L.ndim == 1:
            L = L[None, :]
        if L.ndim != 2 or L.shape[1] != self.n_inputs:
            raise width_error(np.shape(features), self.n_inputs)
        return self._session.run([OUTPUT_NAME], {self._input: L})[0]

    def classify(self, features: np.ndarray) -> tuple[str, float]:
        """Shape and confidence of one contact, ``features`` shape (W,); ``('', nan)`` if a
        used feature is NaN."""
        if np.shape(features) != (self.n_inputs,):
            raise width_error(np.shape(features), self.n_inputs)
        self._one[0] = features
        p = self._session.run([OUTPUT_NAME], {self._input: self._one})[0][0]
        best = int(np.argmax(p))
        if not math.isfinite(float(p[best])) or np.isnan(p).any():
            return "", math.nan
        return self.class_names[best], float(p[best])
