"""Shape classifier with the 4-fold symmetry q4: generator, input widths, Hu-only vs Q4 accuracy."""

from __future__ import annotations

import math

import numpy as np
import pytest

from optitac_edge.calibration.shape_fit import (
    PAPER_SUBSETS,
    Q4_SUBSETS,
    ShapeFitSettings,
    evaluate_model,
    fit_shape_model,
)
from optitac_edge.calibration.shape_mixtures import gmm_per_class, gmm_unsupervised
from optitac_edge.core.moments import q4_moment
from optitac_edge.core.shapes.evaluate import ShapeClassifier
from optitac_edge.core.shapes.features import shape_features
from optitac_edge.core.shapes.model import ShapeModel, subset_name
from optitac_edge.sim.synthetic_shapes import DEFAULT_GRID, shape_mask, synthetic_features

pytest.importorskip("sklearn")

NAMES = ("circle", "square")
#: Small shapes under a 1 mm skin blur: circles and squares differ little in Hu's invariants.
BLURRED = {"shapes": NAMES, "size_mm": (4.0, 6.0), "blur_mm": 1.0}


@pytest.fixture(scope="module")
def blurred() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Calibration day (seed 11) and evaluation day (seed 12), 40 presses per class each."""
    f_cal, l_cal = synthetic_features(40, seed=11, **BLURRED)
    f_eval, l_eval = synthetic_features(40, seed=12, **BLURRED)
    return f_cal, l_cal, f_eval, np.array([NAMES.index(s) for s in l_eval])


def test_q4_of_the_synthetic_shapes_closed_forms() -> None:
    q = {}
    for shape, size in (("circle", 8.0), ("square", 8.0), ("ellipse", 9.0), ("triangle", 8.0)):
        q[shape] = [q4_moment(shape_mask(shape, 0.7, -1.3, a, size), DEFAULT_GRID)
                    for a in (0.0, 17.0, 30.0, 45.0)]
    r = 1 / 0.6
    assert max(q["circle"]) < 3e-3 and max(q["triangle"]) < 3e-3
    np.testing.assert_allclose(q["square"], 1 / 60, rtol=0.05)  # rotation invariant
    np.testing.assert_allclose(q["ellipse"], (r - 1 / r) ** 2 / (8 * math.pi ** 2), rtol=0.05)
    assert math.isnan(q4_moment(np.zeros((100, 100), bool), DEFAULT_GRID))


def test_synthetic_features_layout() -> None:
    f, labels = synthetic_features(3, seed=5)
    assert f.shape == (15, 8) and labels.shape == (15,)
    assert np.all(f[:, 7] >= 0)
    edge_q4 = f[labels == "edge", 7].min()
    assert edge_q4 > 0.2 > f[labels != "edge", 7].max()  # an edge bar is strongly 4-fold


def test_subset_names() -> None:
    assert [subset_name(s) for s in Q4_SUBSETS] == ["M1M2Q4", "M1M3Q4", "M1M2M3Q4", "M1-M7Q4"]
    assert subset_name((0, 1, 2)) == "M1M2M3" and subset_name(tuple(range(7))) == "M1-M7"


@pytest.mark.parametrize("subset", Q4_SUBSETS)
def test_q4_models_classify_and_onnx(blurred, subset, tmp_path) -> None:
    """Per-frame classify() and ONNX agree with predict_proba on Q4 models (incl. NaN q4)."""
    f_cal, l_cal, _, _ = blurred
    y = np.array([NAMES.index(s) for s in l_cal])
    model = gmm_per_class(shape_features(f_cal), y, NAMES, subset, seed=0)[0]
    rows = np.vstack([f_cal, [[0.8, 4.0, 6.0, 8.0, 1.0, 1.0, 1.0, np.nan]], np.full((1, 8), 1e300)])
    clf = ShapeClassifier(model)
    p = clf.predict_proba(rows)
    assert np.isnan(p[-2]).all()
    for row, pr in zip(rows, p):
        shape, conf = clf.classify(row)
        if np.isnan(pr).any():
            assert shape == "" and math.isnan(conf)
        else:
            assert shape == NAMES[int(np.argmax(pr))] and abs(conf - pr.max()) <= 1e-12
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnx")
    from optitac_edge.calibration.onnx_export import export_onnx
    from optitac_edge.core.shapes.onnx_runtime import OnnxShapeClassifier

    onnx_p = OnnxShapeClassifier(export_onnx(model, tmp_path / "m.onnx")).predict_proba(rows)
    np.testing.assert_array_equal(np.isnan(onnx_p), np.isnan(p))
    assert np.nanmax(np.abs(onnx_p - p)) <= 1e-12


def test_input_width_enforced(blurred, tmp_path) -> None:
    f_cal, l_cal, _, _ = blurred
    y = np.array([NAMES.index(s) for s in l_cal])
    m8 = gmm_unsupervised(shape_features(f_cal), y, NAMES, (0, 1, 7), seed=0)[0]
    m7 = gmm_unsupervised(shape_features(f_cal[:, :7]), y, NAMES, (0, 1), seed=0)[0]
    assert (m8.n_inputs, m7.n_inputs) == (8, 7)
    c8, c7 = ShapeClassifier(m8), ShapeClassifier(m7)
    for clf, wrong, msg in ((c8, f_cal[:, :7], "takes 8 features"),
                            (c7, f_cal, "takes 7 features")):
        with pytest.raises(ValueError, match=msg):
            clf.classify(wrong[0])
        with pytest.raises(ValueError, match=msg):
            clf.predict_proba(wrong)
    # same subset, Hu columns only: identical posteriors whatever q4 is
    m8hu = gmm_unsupervised(shape_features(f_cal), y, NAMES, (0, 1), seed=0)[0]
    np.testing.assert_array_equal(ShapeClassifier(m8hu).predict_proba(f_cal),
                                  c7.predict_proba(f_cal[:, :7]))
    with pytest.raises(ValueError, match="subset"):
        ShapeModel.from_bundle(*m7.to_bundle()[:1], {**m7.to_bundle()[1],
                                                     "subset": np.array([0, 7])})


def test_hu_only_fit_and_version1_bundle(blurred) -> None:
    """A 7-wide input searches the paper's subsets only; version-1 bundles load as 7-wide."""
    f_cal, l_cal, f_eval, _ = blurred
    r = fit_shape_model(f_cal[:, :7], l_cal, settings=ShapeFitSettings(seed=0, cv_folds=2,
                                                                     subsets=PAPER_SUBSETS[:3]))
    assert r.model.n_inputs == 7
    with pytest.raises(ValueError, match="Q4"):
        fit_shape_model(f_cal[:, :7], l_cal, settings=ShapeFitSettings(subsets=((0, 1, 7),)))
    meta, arrays = r.model.to_bundle()
    assert meta["version"] == 2 and meta["n_inputs"] == 7
    v1 = {k: v for k, v in meta.items() if k not in ("n_inputs", "q4_floor")}
    old = ShapeModel.from_bundle({**v1, "version": 1}, arrays)
    assert old.n_inputs == 7
    np.testing.assert_array_equal(ShapeClassifier(old).predict_proba(f_eval[:, :7]),
                                  ShapeClassifier(r.model).predict_proba(f_eval[:, :7]))


def test_q4_separates_blurred_circle_and_square(blurred) -> None:
    """Calibrate on one day's presses, evaluate on another's: Q4 beats Hu-only by a clear margin."""
    f_cal, l_cal, f_eval, y_eval = blurred
    metrics = {}
    for tag, subsets in (("hu", PAPER_SUBSETS), ("q4", Q4_SUBSETS), ("all", None)):
        r = fit_shape_model(f_cal, l_cal, settings=ShapeFitSettings(seed=0, subsets=subsets))
        metrics[tag] = (r, evaluate_model(r.model, f_eval, y_eval))
    hu, q4 = metrics["hu"][1], metrics["q4"][1]
    assert hu.average_diagonal <= 0.9  # the setting confuses Hu-only models
    for name in NAMES:
        assert q4.f1[name] >= hu.f1[name] + 0.1
    assert min(q4.f1.values()) >= 0.95
    r_all, all_metrics = metrics["all"]
    assert r_all.model.subset_name.endswith("Q4")  # chosen by CV on the calibration presses
    assert all_metrics.average_diagonal >= 0.95
