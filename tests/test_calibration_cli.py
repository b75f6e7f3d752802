"""The calibration steps, evaluation, ONNX export and report, end to end through the CLI."""

from __future__ import annotations

import re
import shutil

import numpy as np
import pytest

from optitac_edge.calibration.measure import measure_recording
from optitac_edge.cli import main
from optitac_edge.core.corrections import ContactCorrector
from optitac_edge.io.bundle_file import load_bundle
from optitac_edge.io.recording import Recording

SIZE = ["--width", "320", "--height", "240"]


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    """Calibrated on day 1 (seeds 1x), evaluation recordings of day 2 (seeds 2x)."""
    d = tmp_path_factory.mktemp("calcli")
    for name, seed in (("rest", 10), ("seen", 11), ("widths", 12), ("shapes", 13)):
        assert main(["sim", str(d / f"cal_{name}"), "--scenario", name, "--seed", str(seed), "--day", "1",
                     *SIZE]) == 0
    for name, seed in (("unseen", 21), ("repeat", 22)):
        assert main(["sim", str(d / f"eval_{name}"), "--scenario", name, "--seed", str(seed), "--day", "2",
                     *SIZE]) == 0
    cal = d / "cal.npz"
    assert main(["calibrate", "fibers", str(d / "cal_rest"), "-o", str(cal)]) == 0
    assert main(["calibrate", "centroid", str(d / "cal_seen"), "--cal", str(cal)]) == 0
    assert main(["calibrate", "width", str(d / "cal_widths"), "--cal", str(cal)]) == 0
    assert main(["calibrate", "shapes", str(d / "cal_shapes"), "--cal", str(cal)]) == 0
    return d, cal


def _figures(text: str, label: str) -> tuple[float, float]:
    match = re.search(label + r"[^\n]*?RMSE x ([0-9.]+) mm, y ([0-9.]+) mm", text)
    assert match, text
    return float(match.group(1)), float(match.group(2))


def test_bundle_holds_every_model(calibrated):
    _, cal = calibrated
    bundle = load_bundle(cal)
    assert {"centroid", "width", "shapes"} <= set(bundle.extra_meta)
    corrector = ContactCorrector(bundle)
    assert corrector.calibrated and corrector.shapes is not None
    assert bundle.extra_arrays["centroid/error_x"].shape == (1000, 1000)


def test_calibration_improves_unseen_centroid_on_another_day(calibrated, capsys):
    d, cal = calibrated
    rec = Recording(d / "eval_unseen")
    bundle = load_bundle(cal)
    raw = measure_recording(rec, bundle, corrected=False, progress=False)
    from optitac_edge.calibration.evaluation import centroid_accuracy

    before = centroid_accuracy(raw, rec.truth)
    capsys.readouterr()
    assert main(["evaluate", str(d / "eval_unseen"), "--cal", str(cal)]) == 0
    out = capsys.readouterr().out
    x, y = _figures(out, "centroid")
    assert x < 0.08 and y < 0.08, out
    assert x < before.rmse_x / 3 and y < before.rmse_y / 3
    assert "false contacts on 0/" in out


def test_repeatability_is_reported_per_position(calibrated, capsys):
    d, cal = calibrated
    assert main(["evaluate", str(d / "eval_repeat"), "--cal", str(cal)]) == 0
    out = capsys.readouterr().out
    assert out.count(": 10, ") == 5  # five positions of ten presses
    ranges = re.search(r"average range x ([0-9.]+) mm, y ([0-9.]+) mm", out)
    assert float(ranges.group(1)) < 0.08 and float(ranges.group(2)) < 0.08


def test_onnx_export_classifies_like_the_numpy_model(calibrated, capsys, tmp_path):
    d, cal = calibrated
    onnx_path = tmp_path / "shapes.onnx"
    assert main(["export-onnx", str(cal), "-o", str(onnx_path)]) == 0
    rec = Recording(d / "cal_shapes")
    bundle = load_bundle(cal)
    a = measure_recording(rec, bundle, progress=False)
    b = measure_recording(rec, bundle, progress=False, shape_backend="onnx", onnx_path=str(onnx_path))
    assert a.contact.sum() > 100
    np.testing.assert_array_equal(a.shape, b.shape)
    np.testing.assert_allclose(a.confidence, b.confidence, atol=1e-6, equal_nan=True)
    capsys.readouterr()
    assert main(["evaluate", str(d / "cal_shapes"), "--cal", str(cal), "--shape-backend", "onnx",
                 "--onnx", str(onnx_path)]) == 0
    assert "average diagonal" in capsys.readouterr().out


def test_report_writes_the_figures(calibrated, tmp_path):
    d, cal = calibrated
    out = tmp_path / "report"
    assert main(["report", str(cal), "-o", str(out), "--unseen", str(d / "eval_unseen"),
                 "--repeat", str(d / "eval_repeat")]) == 0
    names = {p.name for p in out.glob("*.png")}
    assert names == {"error_maps.png", "seen_scatter.png", "unseen_scatter.png", "repeatability.png",
                     "width_fit.png", "confusion.png", "hu_scatter.png"}
    index = (out / "index.md").read_text()
    assert all(name in index for name in names)
    assert all((out / n).stat().st_size > 10_000 for n in names)


def test_steps_refuse_recordings_without_truth_or_models(calibrated, capsys, tmp_path):
    d, cal = calibrated
    no_truth = tmp_path / "no_truth"
    shutil.copytree(d / "cal_rest", no_truth)
    (no_truth / "truth.csv").unlink()
    code = main(["calibrate", "centroid", str(no_truth), "--cal", str(cal)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "needs truth.csv" in err and "\n" not in err
    plain = tmp_path / "plain.npz"
    assert main(["calibrate", "fibers", str(d / "cal_rest"), "-o", str(plain)]) == 0
    capsys.readouterr()
    assert main(["export-onnx", str(plain), "-o", str(tmp_path / "x.onnx")]) == 2
    assert "no shape model" in capsys.readouterr().err


def test_numpy_and_onnx_mixtures_match_sklearn_on_simulated_calibration_presses(calibrated, tmp_path):
    """The runtime evaluators agree with scikit-learn's predict_proba to 1e-6 on real calibration data."""
    from optitac_edge.calibration.evaluation import detected_rows
    from optitac_edge.calibration.onnx_export import export_onnx
    from optitac_edge.calibration.shape_mixtures import gmm_per_class, gmm_unsupervised
    from optitac_edge.core.shapes.evaluate import ShapeClassifier
    from optitac_edge.core.shapes.features import shape_features
    from optitac_edge.core.shapes.onnx_runtime import OnnxShapeClassifier

    d, cal = calibrated
    rec = Recording(d / "cal_shapes")
    m = measure_recording(rec, load_bundle(cal), corrected=False, progress=False)
    rows = np.flatnonzero(detected_rows(m, rec.truth))
    raw = m.features[rec.truth.frame[rows]]
    names = tuple(sorted(set(rec.truth.shape[rows])))
    y = np.array([names.index(s) for s in rec.truth.shape[rows]])
    f = shape_features(raw)
    model, gm = gmm_unsupervised(f, y, names, (0, 1, 2), seed=0)
    z = (f[:, [0, 1, 2]] - model.mean) / model.std
    reference = gm.predict_proba(z) @ np.eye(len(names))[model.component_class]
    np.testing.assert_allclose(ShapeClassifier(model).predict_proba(raw), reference, atol=1e-6)
    model, estimators, priors = gmm_per_class(f, y, names, (0, 1, 2, 7), seed=0)
    z = (f[:, [0, 1, 2, 7]] - model.mean) / model.std
    logp = np.stack([e.score_samples(z) for e in estimators], axis=1) + np.log(priors)
    reference = np.exp(logp - logp.max(axis=1, keepdims=True))
    reference /= reference.sum(axis=1, keepdims=True)
    ours = ShapeClassifier(model).predict_proba(raw)
    np.testing.assert_allclose(ours, reference, atol=1e-6)
    export_onnx(model, tmp_path / "m.onnx")
    np.testing.assert_allclose(OnnxShapeClassifier(tmp_path / "m.onnx").predict_proba(raw), ours, atol=1e-6)
