"""Put calibration models into a bundle (``extra_meta`` / ``extra_arrays``, see docs/formats.md).

The runtime reads them back with :class:`optitac_edge.core.corrections.ContactCorrector`.
"""

from __future__ import annotations

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.centroid_map import CentroidErrorMap
from optitac_edge.core.corrections import CENTROID_KEY, DEPTH_KEY, SHAPES_KEY, WIDTH_KEY
from optitac_edge.core.depth_model import DepthForceModel
from optitac_edge.core.shapes.model import ShapeModel
from optitac_edge.core.width_model import WidthModel


def with_centroid_map(bundle: CalibrationBundle, error_map: CentroidErrorMap) -> CalibrationBundle:
    meta, arrays = error_map.to_bundle()
    kept = {k: v for k, v in bundle.extra_arrays.items() if not k.startswith(CENTROID_KEY + "/")}
    return bundle.with_updates(extra_meta={**bundle.extra_meta, CENTROID_KEY: meta},
                               extra_arrays={**kept, **arrays})


def with_width_model(bundle: CalibrationBundle, model: WidthModel) -> CalibrationBundle:
    return bundle.with_updates(extra_meta={**bundle.extra_meta, WIDTH_KEY: model.to_bundle()})


def with_shape_model(bundle: CalibrationBundle, model: ShapeModel) -> CalibrationBundle:
    meta, arrays = model.to_bundle()
    kept = {k: v for k, v in bundle.extra_arrays.items() if not k.startswith(SHAPES_KEY + "/")}
    return bundle.with_updates(extra_meta={**bundle.extra_meta, SHAPES_KEY: meta},
                               extra_arrays={**kept, **{f"{SHAPES_KEY}/{k}": v for k, v in arrays.items()}})


def with_depth_model(bundle: CalibrationBundle, model: DepthForceModel) -> CalibrationBundle:
    return bundle.with_updates(extra_meta={**bundle.extra_meta, DEPTH_KEY: model.to_bundle()})
