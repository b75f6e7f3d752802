"""Calibration models applied to each reported contact: centroid error map, width model, shape,
depth and force.

The models live in the bundle (``extra_meta`` / ``extra_arrays``, see
docs/formats.md) and are added by ``optitac-edge calibrate centroid|width|shapes``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.centroid_map import CentroidErrorMap
from optitac_edge.core.depth_model import DepthForceModel
from optitac_edge.core.width_model import WidthModel
from optitac_edge.errors import BundleError

if TYPE_CHECKING:
    from optitac_edge.core.contact import ContactEstimate
    from optitac_edge.core.shapes.evaluate import ShapeClassifier
    from optitac_edge.core.shapes.model import ShapeModel
    from optitac_edge.core.shapes.onnx_runtime import OnnxShapeClassifier

CENTROID_KEY, WIDTH_KEY, SHAPES_KEY, DEPTH_KEY = "centroid", "width", "shapes", "depth"


def _arrays_with_prefix(bundle: CalibrationBundle, prefix: str) -> dict[str, Any]:
    return {k: v for k, v in bundle.extra_arrays.items() if k.startswith(prefix + "/")}


def load_shape_model(bundle: CalibrationBundle) -> ShapeModel | None:
    """The bundle's shape model, or None."""
    if SHAPES_KEY not in bundle.extra_meta:
        return None
    from optitac_edge.core.shapes.model import ShapeModel

    arrays = {k[len(SHAPES_KEY) + 1:]: v for k, v in _arrays_with_prefix(bundle, SHAPES_KEY).items()}
    try:
        return ShapeModel.from_bundle(bundle.extra_meta[SHAPES_KEY], arrays)
    except (KeyError, ValueError, TypeError, AttributeError, IndexError) as exc:
        raise BundleError(f"bundle has an invalid shape model ({type(exc).__name__}: {exc})") from None


def read_models(bundle: CalibrationBundle) -> tuple[CentroidErrorMap | None, WidthModel | None,
                                                    DepthForceModel | None, ShapeModel | None]:
    """The bundle's centroid map, width model, depth model and shape model (None where absent).

    Raises
    ------
    BundleError
        Naming the model that is not what ``calibrate`` writes (a crafted or damaged bundle).
    """
    meta = bundle.extra_meta
    parsers: dict[str, Any] = {
        CENTROID_KEY: lambda v: CentroidErrorMap.from_bundle(v, dict(bundle.extra_arrays)),
        WIDTH_KEY: WidthModel.from_bundle, DEPTH_KEY: DepthForceModel.from_bundle}
    models: dict[str, Any] = {}
    for key, parse in parsers.items():
        try:
            models[key] = parse(meta[key]) if key in meta else None
        except (KeyError, ValueError, TypeError, AttributeError, IndexError) as exc:
            raise BundleError(f"bundle has an invalid {key} model ({type(exc).__name__}: {exc})") from None
    return models[CENTROID_KEY], models[WIDTH_KEY], models[DEPTH_KEY], load_shape_model(bundle)


class ContactCorrector:
    """Applies the bundle's calibration models to a contact estimate, in place.

    Parameters
    ----------
    bundle : CalibrationBundle
    shape_backend : {"numpy", "onnx"}
        Evaluate the shape model in closed form (numpy) or with onnxruntime.
    onnx_path : path-like, optional
        The exported model for ``shape_backend="onnx"``.
    """

    def __init__(self, bundle: CalibrationBundle, shape_backend: str = "numpy",
                 onnx_path: str | None = None) -> None:
        self.centroid, self.width, self.depth, shape_model = read_models(bundle)
        self.shapes: ShapeClassifier | OnnxShapeClassifier | None = None
        if shape_model is not None:
            if shape_backend == "onnx":
                from optitac_edge.core.shapes.onnx_runtime import OnnxShapeClassifier

                if onnx_path is None:
                    raise BundleError("the onnx shape backend needs the exported model (export-onnx)")
                self.shapes = OnnxShapeClassifier(onnx_path)
            elif shape_backend == "numpy":
                from optitac_edge.core.shapes.evaluate import ShapeClassifier

                self.shapes = ShapeClassifier(shape_model)
            else:
                raise BundleError(f"unknown shape backend {shape_backend!r} (numpy or onnx)")

    def kernel_arrays(self) -> dict[str, Any] | None:
        """The models as the compiled kernel reads them (:mod:`optitac_edge.core.compiled`), or None when
        one is not the kernel's to evaluate (the ONNX shape backend): then this corrector runs in Python."""
        from optitac_edge.core.shapes.evaluate import ShapeClassifier

        if self.shapes is not None and not isinstance(self.shapes, ShapeClassifier):
            return None
        out: dict[str, Any] = {}
        for model in (self.centroid, self.width, self.depth, self.shapes):
            if model is not None:
                out.update(model.kernel_arrays())
        return out

    @property
    def active(self) -> bool:
        return (self.centroid is not None or self.width is not None or self.shapes is not None
                or self.depth is not None)

    @property
    def calibrated(self) -> bool:
        """Centroid and width both calibrated."""
        return self.centroid is not None and self.width is not None

    def apply(self, est: ContactEstimate) -> None:
        """Correct one contact (a :class:`~optitac_edge.core.contact.ContactEstimate` with contact)."""
        if self.depth is not None:  # first: it reads the raw widths and position it was fitted on
            self.depth.apply(est)
        if self.width is not None:  # before the centroid map: it reads the raw position it was fitted on
            est.major_mm, est.minor_mm = self.width.correct(est.major_mm, est.minor_mm, est.x_mm, est.y_mm)
        if self.centroid is not None:
            est.x_mm, est.y_mm = self.centroid.correct(est.x_mm, est.y_mm)
        if self.shapes is not None:
            features = est.features if self.shapes.n_inputs == est.features.size else est.hu
            est.shape, est.confidence = self.shapes.classify(features)
