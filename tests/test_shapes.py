"""Shape classifier: feature transform, fitting, numpy / sklearn / ONNX agreement, bundle form.

Inputs are the pipeline's 8-wide shape features ``[log-Hu x 7, q4]``; q4-specific
tests (the q4 generator, Hu-only vs Q4 accuracy, 7-wide models) are in test_shapes_q4.py.
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest

from optitac_edge.calibration.folds import stratified_group_split
from optitac_edge.calibration.shape_fit import (
    ALL_SUBSETS,
    Q4_SUBSETS,
    ShapeFitSettings,
    evaluate_model,
    fit_shape_model,
)
from optitac_edge.calibration.shape_mixtures import fit_supervised, fit_unsupervised, gmm_per_class, gmm_unsupervised
from optitac_edge.core.moments import log_hu
from optitac_edge.core.shapes.evaluate import ShapeClassifier
from optitac_edge.core.shapes.features import LOG_HU_CAP, Q4_FLOOR, shape_features
from optitac_edge.core.shapes.model import ShapeModel
from optitac_edge.io.recording import SHAPES
from optitac_edge.sim.synthetic_shapes import synthetic_features

pytest.importorskip("sklearn")

NAMES = tuple(sorted(SHAPES))
EDGE_ROWS = np.array([
    [np.nan] * 8, [0.0] * 8, [np.inf] * 8, [-np.inf] * 8, [1e300] * 8, [-1e300] * 8,
    [0.8, 65.6, 33.5, 34.9, 69.6, -68.2, 69.2, 1e-18],  # centred circle: rounding noise
    [0.8, 4.4, np.nan, 8.0, 1.0, 1.0, 1.0, 0.0167],
    [0.8, 4.4, 6.0, 8.0, 1.0, 1.0, 1.0, np.nan],
])


@pytest.fixture(scope="module")
def data() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Features of 5 x 40 random shapes, 2 frames per press (the second perturbed:
    log-Hu by 0.002, q4 by 0.2 %)."""
    hu, labels = synthetic_features(40, seed=3)
    rng = np.random.default_rng(4)
    hu2 = hu + rng.normal(0.0, 0.002, hu.shape) * np.r_[np.ones(7), hu[:, 7:].mean()]
    groups = np.arange(hu.shape[0])
    return np.vstack([hu, hu2]), np.concatenate([labels, labels]), np.concatenate([groups, groups])


@pytest.fixture(scope="module")
def report(data):
    hu, labels, groups = data
    return fit_shape_model(hu, labels, groups=groups, settings=ShapeFitSettings(seed=0, holdout=0.3))


def _class_index(labels: np.ndarray) -> np.ndarray:
    return np.array([NAMES.index(s) for s in labels])


# -- feature transform ------------------------------------------------------------------------

def test_features_special_values() -> None:
    f = shape_features(EDGE_ROWS)
    C, lo, hi = LOG_HU_CAP, math.log(Q4_FLOOR), math.log(1e6 + Q4_FLOOR)
    assert np.isnan(f[0]).all()
    np.testing.assert_array_equal(f[1], [0.0, C, C, C, 0.0, 0.0, 0.0, lo])  # h == 0 (log_hu's 0)
    np.testing.assert_array_equal(f[2], [C, C, C, C, 0.0, 0.0, 0.0, hi])
    np.testing.assert_array_equal(f[3], [-C, -C, -C, -C, 0.0, 0.0, 0.0, lo])
    np.testing.assert_array_equal(f[4], [C, C, C, C, 0.0, 0.0, 0.0, hi])
    np.testing.assert_array_equal(f[5], [-C, -C, -C, -C, 0.0, 0.0, 0.0, lo])
    np.testing.assert_allclose(f[6], [0.8, C, C, C, 0.0, 0.0, 0.0, lo], rtol=0, atol=1e-14)
    np.testing.assert_allclose(f[7, 7], math.log(0.0167 + Q4_FLOOR), rtol=1e-15)
    assert np.isnan(f[7, 2]) and np.isfinite(np.delete(f[7], 2)).all()
    assert np.isnan(f[8, 7]) and np.isfinite(f[8, :7]).all()
    assert np.all(np.abs(f[:, :7][np.isfinite(f[:, :7])]) <= C)
    np.testing.assert_array_equal(shape_features(EDGE_ROWS[:, :7]), f[:, :7])  # log-Hu only


def test_features_from_raw_invariants() -> None:
    """Floor |h| at 1e-20: +-1e-33 noise maps to the same value as h == 0; symlog continuous."""
    h = np.array([0.16, 1e-33, 1e-33, 1e-33, 1e-33, -1e-33, 1e-33])
    f = shape_features(log_hu(h))
    np.testing.assert_array_equal(f, shape_features(log_hu(np.array([0.16, 0, 0, 0, 0, 0, 0]))))
    h5 = np.array([-1e-3, -1e-15, -1e-21, 0.0, 1e-21, 1e-15, 1e-3])
    rows = np.tile([0.16, 1e-2, 1e-3, 1e-4, 0.0, 0.0, 0.0], (h5.size, 1))
    rows[:, 4] = h5
    f5 = shape_features(np.array([log_hu(r) for r in rows]))[:, 4]
    np.testing.assert_allclose(f5, [-17.0, -5.0, 0.0, 0.0, 0.0, 5.0, 17.0], atol=1e-12)
    assert np.all(np.diff(f5) >= 0)  # increasing in h through 0
    np.testing.assert_allclose(shape_features(log_hu(rows[0]))[:4], [-math.log10(0.16), 2, 3, 4])


def test_features_shape_checked() -> None:
    assert shape_features(np.zeros(7)).shape == (7,)
    assert shape_features(np.zeros((2, 3, 7))).shape == (2, 3, 7)
    assert shape_features(np.zeros((2, 3, 8))).shape == (2, 3, 8)
    for bad in (np.zeros((4, 6)), np.zeros((4, 9)), np.float64(1.0)):
        with pytest.raises(ValueError):
            shape_features(bad)


# -- numpy evaluator vs scikit-learn -----------------------------------------------------------

@pytest.mark.parametrize("subset", [(0, 1, 2), (0, 1), tuple(range(7)), *Q4_SUBSETS])
def test_unsupervised_matches_sklearn(data, subset) -> None:
    hu, labels, _ = data
    f = shape_features(hu)
    model, gm = gmm_unsupervised(f, _class_index(labels), NAMES, subset, seed=1)
    z = (f[:, list(subset)] - model.mean) / model.std
    onehot = np.eye(len(NAMES))[model.component_class]
    ref = gm.predict_proba(z) @ onehot
    ours = ShapeClassifier(model).predict_proba(hu)
    assert np.abs(ours - ref).max() < 1e-9
    np.testing.assert_allclose(ours.sum(axis=1), 1.0, atol=1e-12)


@pytest.mark.parametrize("subset", [(0, 1, 2), (0, 1, 3), tuple(range(7)), *Q4_SUBSETS])
def test_supervised_matches_sklearn(data, subset) -> None:
    hu, labels, _ = data
    f = shape_features(hu)
    model, ests, priors = gmm_per_class(f, _class_index(labels), NAMES, subset, seed=1)
    z = (f[:, list(subset)] - model.mean) / model.std
    logp = np.stack([e.score_samples(z) for e in ests], axis=1) + np.log(priors)
    ref = np.exp(logp - logp.max(axis=1, keepdims=True))
    ref /= ref.sum(axis=1, keepdims=True)
    ours = ShapeClassifier(model).predict_proba(hu)
    assert np.abs(ours - ref).max() < 1e-9


def test_classify_matches_predict_proba(report, data) -> None:
    hu = np.vstack([data[0], EDGE_ROWS])
    for model in (report.unsupervised.holdout_model, report.supervised.holdout_model, report.model):
        clf = ShapeClassifier(model)
        p = clf.predict_proba(hu)
        names = clf.predict(hu)
        for row, pr, name in zip(hu, p, names):
            shape, conf = clf.classify(row)
            if np.isnan(pr).any():
                assert shape == "" and math.isnan(conf) and name == ""
            else:
                assert shape == name == model.class_names[int(np.argmax(pr))]
                assert conf == pytest.approx(pr.max(), abs=1e-12)


def test_classify_is_fast(report, data) -> None:
    clf = ShapeClassifier(report.model)
    x = data[0][0].copy()
    clf.classify(x)
    n = 2000
    t0 = time.perf_counter()
    for _ in range(n):
        clf.classify(x)
    per_call_us = (time.perf_counter() - t0) / n * 1e6
    assert per_call_us < 200.0  # ~10 us on a desktop; generous for loaded CI machines


# -- fitting protocol --------------------------------------------------------------------------

def test_holdout_disjoint_and_train_only(report, data) -> None:
    hu, labels, groups = data
    tr, te = report.train_index, report.test_index
    assert np.intersect1d(tr, te).size == 0
    assert np.union1d(tr, te).size == hu.shape[0]
    assert not set(groups[tr]) & set(groups[te])  # presses never split
    assert set(labels[te]) == set(NAMES)
    y = _class_index(labels)
    f = shape_features(hu)
    for kind_report, fitter in ((report.unsupervised, fit_unsupervised),
                                (report.supervised, fit_supervised)):
        m = kind_report.holdout_model
        opts = {"seed": 0, **({"n_init": 5, "reg_covar": 1e-6} if fitter is fit_unsupervised
                              else {"reg_covar": 1e-4})}
        again = fitter(f[tr], y[tr], NAMES, tuple(m.subset.tolist()), **opts)
        np.testing.assert_array_equal(again.means, m.means)  # fit on the training rows only
        again_metrics = evaluate_model(m, hu[te], y[te])
        np.testing.assert_array_equal(again_metrics.confusion, kind_report.holdout.confusion)
        assert kind_report.holdout.n == te.size
        assert [r.subset for r in kind_report.subsets] == list(ALL_SUBSETS)


def test_report_choice_and_json(report) -> None:
    assert report.kind in ("gmm_unsupervised", "gmm_per_class")
    assert report.model.kind == report.kind
    assert tuple(report.model.subset.tolist()) == report.chosen.selected
    d = json.loads(json.dumps(report.to_dict(), allow_nan=False))
    assert set(d["unsupervised"]["subsets"]) == set(d["supervised"]["subsets"]) == {
        "M1M2", "M1M3", "M1M2M3", "M1M2M4", "M1M2M5", "M1M2M6", "M1M2M7", "M1-M7",
        "M1M2Q4", "M1M3Q4", "M1M2M3Q4", "M1-M7Q4"}
    assert d["n_inputs"] == report.model.n_inputs == 8
    if report.supervised.cv_score <= report.unsupervised.cv_score:
        assert report.kind == "gmm_unsupervised"  # ties go to the paper's


def test_synthetic_shapes_accuracy(report) -> None:
    """Real log-Hu of rasterised shapes: the supervised mixture separates them."""
    assert report.supervised.holdout.average_diagonal >= 0.95
    assert report.unsupervised.holdout.average_diagonal >= 0.6
    assert report.chosen.holdout.average_diagonal >= 0.95
    assert min(report.supervised.holdout.f1.values()) >= 0.9


def test_separable_blobs_both_kinds() -> None:
    rng = np.random.default_rng(7)
    centres = np.array([[0.2, 0.5, 3.0], [0.8, 4.5, 5.0], [0.78, 4.5, 9.0],
                        [0.74, 2.1, 6.0], [0.71, 3.5, 2.3]])
    hu = np.concatenate([c + rng.normal(0, [0.01, 0.2, 0.3], (60, 3)) for c in centres])
    hu = np.hstack([hu, rng.normal(5.0, 1.0, (hu.shape[0], 4)), rng.uniform(0, 1, (300, 1))])
    labels = np.repeat(np.array(["edge", "circle", "square", "ellipse", "triangle"]), 60)
    r = fit_shape_model(hu, labels, settings=ShapeFitSettings(seed=0, subsets=((0, 1, 2), (0, 1)), cv_folds=2))
    assert r.unsupervised.holdout.average_diagonal >= 0.95
    assert r.supervised.holdout.average_diagonal >= 0.95


def test_fit_drops_nan_rows(data) -> None:
    hu, labels, _ = data
    hu = hu[::2].copy()
    labels = labels[::2]
    hu[:3] = np.nan
    r = fit_shape_model(hu, labels, settings=ShapeFitSettings(seed=1, subsets=((0, 1, 2),), cv_folds=2,
                                                           refit=False))
    assert r.n_dropped == 3
    assert not np.isin(np.arange(3), np.concatenate([r.train_index, r.test_index])).any()
    assert r.model is r.chosen.holdout_model


def test_stratified_group_split() -> None:
    y = np.repeat(np.arange(3), 20)
    groups = np.arange(60) // 4  # 5 presses per class
    rest, held = stratified_group_split(y, groups, 0.3, np.random.default_rng(0))
    assert not set(groups[rest]) & set(groups[held])
    for c in range(3):
        assert (y[held] == c).sum() == 8 and (y[rest] == c).sum() == 12


# -- model form --------------------------------------------------------------------------------

def test_bundle_round_trip(report, data, tmp_path) -> None:
    model = report.model
    meta, arrays = model.to_bundle()
    assert all(isinstance(a, np.ndarray) and a.dtype.kind in "if" for a in arrays.values())
    np.savez(tmp_path / "m.npz", **arrays)
    with np.load(tmp_path / "m.npz", allow_pickle=False) as npz:
        loaded = {k: npz[k] for k in npz.files}
    back = ShapeModel.from_bundle(json.loads(json.dumps(meta)), loaded)
    assert back.kind == model.kind and back.class_names == model.class_names
    for name in arrays:
        np.testing.assert_array_equal(getattr(back, name), getattr(model, name))
    hu = np.vstack([data[0], EDGE_ROWS])
    np.testing.assert_array_equal(ShapeClassifier(back).predict_proba(hu),
                                  ShapeClassifier(model).predict_proba(hu))
    extra_meta, extra_arrays = model.to_calibration_extras()
    assert set(extra_arrays) == {f"shapes/{k}" for k in arrays}
    again = ShapeModel.from_calibration_extras({"other": 1, **extra_meta},
                                               {"x/y": np.zeros(1), **extra_arrays})
    np.testing.assert_array_equal(again.precisions_cholesky, model.precisions_cholesky)
    assert ShapeModel.from_calibration_extras({}, {}) is None
    with pytest.raises(ValueError):
        ShapeModel.from_bundle({**meta, "version": 99}, arrays)
    with pytest.raises(ValueError):
        ShapeModel.from_bundle(meta, {k: v for k, v in arrays.items() if k != "means"})


def test_model_validation(report) -> None:
    meta, arrays = report.model.to_bundle()
    bad = {**arrays, "weights": arrays["weights"] * 2}
    with pytest.raises(ValueError):
        ShapeModel.from_bundle(meta, bad)
    with pytest.raises(ValueError):
        ShapeModel.from_bundle(meta, {**arrays, "subset": np.array([0, 9])})
    with pytest.raises(ValueError):
        ShapeModel.from_bundle(meta, {**arrays, "subset": np.array([0, 8])})
    with pytest.raises(ValueError):
        ShapeModel.from_bundle({**meta, "n_inputs": 6}, arrays)
    with pytest.raises(ValueError):
        ShapeModel.from_bundle(meta, {**arrays, "component_class": arrays["component_class"] + 9})
    assert not report.model.means.flags.writeable


# -- ONNX --------------------------------------------------------------------------------------

def test_onnx_matches_numpy(report, data, tmp_path) -> None:
    pytest.importorskip("onnx")
    pytest.importorskip("onnxruntime")
    from optitac_edge.calibration.onnx_export import export_onnx
    from optitac_edge.core.shapes.onnx_runtime import OnnxShapeClassifier

    hu = np.vstack([data[0], EDGE_ROWS])
    for i, model in enumerate((report.unsupervised.holdout_model,
                               report.supervised.holdout_model, report.model)):
        path = export_onnx(model, tmp_path / f"shapes{i}.onnx")
        onnx_clf, np_clf = OnnxShapeClassifier(path), ShapeClassifier(model)
        assert onnx_clf.class_names == model.class_names
        p_onnx, p_np = onnx_clf.predict_proba(hu), np_clf.predict_proba(hu)
        assert p_onnx.dtype == np.float64 and p_onnx.shape == (hu.shape[0], len(NAMES))
        np.testing.assert_array_equal(np.isnan(p_onnx), np.isnan(p_np))
        assert np.nanmax(np.abs(p_onnx - p_np)) <= 1e-12
        assert onnx_clf.n_inputs == 8
        for row in hu[::25]:
            a, b = onnx_clf.classify(row), np_clf.classify(row)
            assert a[0] == b[0]
            assert (math.isnan(a[1]) and math.isnan(b[1])) or abs(a[1] - b[1]) <= 1e-12
        with pytest.raises(ValueError, match="8 features"):
            onnx_clf.predict_proba(hu[:, :7])
        with pytest.raises(ValueError, match="8 features"):
            onnx_clf.classify(hu[0, :7])
