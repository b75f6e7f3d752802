"""The calibration report: PNG figures like the paper's and a Markdown summary."""

from __future__ import annotations

import io
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.corrections import ContactCorrector
from optitac_edge.errors import OptiTacError, OutputError, missing_extra
from optitac_edge.io.bundle_file import load_bundle
from optitac_edge.io.files import check_output_path, write_file_atomic
from optitac_edge.io.recording import SHAPES, Recording
from optitac_edge.text import fields, plain

if TYPE_CHECKING:
    from optitac_edge.calibration.measure import Measurements
    from optitac_edge.calibration.verdict import Verdict
    from optitac_edge.core.centroid_map import CentroidErrorMap
    from optitac_edge.core.width_model import WidthModel
    from optitac_edge.io.recording import Truth

_COLOURS = {"edge": "tab:red", "circle": "tab:blue", "square": "tab:green", "ellipse": "tab:orange",
            "triangle": "tab:purple"}


def _fit_lines(title: str, fit: dict[str, Any], name_key: str) -> list[str]:
    """A step's summary in one line, and its candidates' held-out figures in another (no raw dicts)."""
    lists = {k: v for k, v in fit.items() if k.endswith("candidates") and isinstance(v, list)}
    lines = [f"{title}: {fields({k: v for k, v in fit.items() if k not in lists})}."]
    for key, candidates in lists.items():
        parts = []
        for c in candidates:
            if not isinstance(c, dict):
                continue
            name = c.get(name_key, "?")
            figure = c.get("expected_rmse", c.get("score_mm", c.get("heldout_rmse_mm")))
            parts.append(f"{name} {plain(figure)}")
        lines.append(f"{title}, {key.replace('_', ' ')} on held-out presses (score): {', '.join(parts)}.")
    return lines


def _plt() -> Any:
    try:
        import matplotlib
    except ImportError:
        raise missing_extra("matplotlib", "the report") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _fibers(ax: Any, bundle: CalibrationBundle) -> None:
    xy = bundle.layout.xy_mm
    ax.scatter(xy[:, 0], xy[:, 1], s=6, c="lightgray", zorder=0, label="fibers")
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")


def array_colour_limit(data: np.ndarray, cm: CentroidErrorMap, radius_mm: float) -> float:
    """The largest |error| of an error map within ``radius_mm`` of the array's centre (1.0 if none):
    the colour scale of the map, so the extrapolated rim cannot wash out the array."""
    xs = cm.x0_mm + cm.step_mm * np.arange(cm.n)
    ys = cm.y0_mm + cm.step_mm * np.arange(cm.n)
    xx, yy = np.meshgrid(xs, ys)
    inside = np.hypot(xx, yy) <= radius_mm
    return float(np.abs(data[inside]).max(initial=0.0)) or 1.0


def _near_presses(cm: CentroidErrorMap, presses: np.ndarray | None, reach_mm: float) -> np.ndarray | None:
    """The error map's cells within ``reach_mm`` of a calibration press, shape (n, n) (None: no presses kept)."""
    if presses is None or presses.size == 0:
        return None
    from scipy.spatial import cKDTree

    xs = cm.x0_mm + cm.step_mm * np.arange(cm.n)
    ys = cm.y0_mm + cm.step_mm * np.arange(cm.n)
    xx, yy = np.meshgrid(xs, ys)
    distance, _ = cKDTree(np.asarray(presses, np.float64).reshape(-1, 2)).query(np.column_stack([xx.ravel(),
                                                                                                  yy.ravel()]))
    return np.asarray(distance <= reach_mm).reshape(cm.n, cm.n)


def _error_maps(plt: Any, bundle: CalibrationBundle, corrector: ContactCorrector, out: Path) -> str | None:
    cm = corrector.centroid
    if cm is None:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.6), constrained_layout=True)
    extent = [cm.x0_mm, cm.x0_mm + cm.step_mm * (cm.n - 1), cm.y0_mm, cm.y0_mm + cm.step_mm * (cm.n - 1)]
    # the colour scale is that of the array: the map is extrapolated beyond the outermost fibers,
    # where its values can be far larger and would wash out the part that matters. Where no press was
    # made (farther than a pitch from every calibration press) the map is a guess: grey, and the
    # presses are marked, so nobody reads a correction where nothing was measured.
    presses = bundle.extra_arrays.get("report/centroid_true")
    pressed = _near_presses(cm, None if presses is None else np.asarray(presses), bundle.layout.pitch_mm)
    cmap = plt.get_cmap("RdBu_r").with_extremes(bad="#d8d8d8")
    for ax, data, name in zip(axes, (cm.error_x, cm.error_y), ("x", "y")):
        lim = array_colour_limit(data, cm, bundle.layout.radius_mm)
        shown = data if pressed is None else np.ma.masked_where(~pressed, data)
        im = ax.imshow(shown, origin="lower", extent=extent, cmap=cmap, vmin=-lim, vmax=lim)
        _fibers(ax, bundle)
        if presses is not None:
            unique = np.unique(np.round(np.asarray(presses), 3), axis=0)
            ax.scatter(unique[:, 0], unique[:, 1], s=4, c="k", marker=".", label="calibration presses")
            ax.legend(loc="upper right", fontsize=7)
        ax.set_title(f"{name} error map (measured − true; grey: no press within a pitch)", fontsize=10)
        fig.colorbar(im, ax=ax, label="mm")
    path = out / "error_maps.png"
    _save(plt, fig, path)
    return path.name


def _scatter(plt: Any, bundle: CalibrationBundle, corrector: ContactCorrector, measured: np.ndarray,
             true: np.ndarray, title: str, path: Path) -> str:
    fig, axes = plt.subplots(1, 2, figsize=(11, 5), constrained_layout=True)
    corrected = (np.array([corrector.centroid.correct(x, y) for x, y in measured])
                 if corrector.centroid is not None else measured)
    for ax, pts, name in zip(axes, (measured, corrected), ("raw", "calibrated")):
        _fibers(ax, bundle)
        ax.scatter(true[:, 0], true[:, 1], s=14, facecolors="none", edgecolors="k", label="true")
        ax.scatter(pts[:, 0], pts[:, 1], s=8, c="tab:red", label="measured")
        rmse = np.sqrt(np.mean((pts - true) ** 2, axis=0))
        ax.set_title(f"{title}, {name}: RMSE x {rmse[0]:.3f}, y {rmse[1]:.3f} mm")
        ax.legend(loc="upper right", fontsize=7)
    _save(plt, fig, path)
    return path.name


def _measure_truth(rec_path: Path, bundle: CalibrationBundle, corrected: bool = False) -> tuple[Measurements, Truth]:
    from optitac_edge.calibration.measure import measure_recording

    rec = Recording(rec_path)
    if rec.truth is None:
        raise OptiTacError(f"{rec_path}: the report needs a recording with truth.csv")
    return measure_recording(rec, bundle, corrected=corrected), rec.truth


@dataclass(frozen=True)
class WrittenReport:
    """What :func:`write_report` wrote: the index's path, and the verdict in it."""

    index: Path
    verdict: Verdict


def write_report(cal: str | Path, out_dir: str | Path, unseen: Path | None = None,
                 repeat: Path | None = None) -> WrittenReport:
    """Write the figures and ``index.md`` into ``out_dir``; returns its path and the verdict written."""
    from optitac_edge.calibration.evaluation import detected_rows

    plt = _plt()
    bundle = load_bundle(cal)
    corrector = ContactCorrector(bundle)
    out = check_output_path(out_dir, directory=True)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out}: {exc.strerror or exc}") from None
    arrays = bundle.extra_arrays
    figures: list[tuple[str, str]] = []
    lines = [f"# Calibration report: `{Path(cal).name}` (id {bundle.calibration_id})", "",
             (f"Built {bundle.created_utc} for {bundle.fibers.width}×{bundle.fibers.height} "
              f"{bundle.fibers.pixel_format} frames; {int((~bundle.fibers.dead).sum())}/{bundle.layout.n_fibers} "
              f"fibers found, dead: {np.flatnonzero(bundle.fibers.dead).tolist() or 'none'}."), ""]

    name = _error_maps(plt, bundle, corrector, out)
    if name:
        figures.append(("Centroid error maps", name))
    if "report/centroid_measured" in arrays:
        figures.append(("Seen presses (calibration data)", _scatter(
            plt, bundle, corrector, arrays["report/centroid_measured"], arrays["report/centroid_true"],
            "seen", out / "seen_scatter.png")))
        lines += _fit_lines("Centroid calibration", bundle.extra_meta.get("centroid_fit") or {}, "fill")
        lines.append("The centroid figures above are the calibration presses', each held out in turn: what a press "
                     "the map was not fitted to may expect. 'evaluate REC' measures presses of another recording.")
    if unseen is not None:
        m, truth = _measure_truth(unseen, bundle)
        rows = np.flatnonzero(detected_rows(m, truth))
        f = truth.frame[rows]
        figures.append(("Unseen presses", _scatter(
            plt, bundle, corrector, np.stack([m.x_mm[f], m.y_mm[f]], 1),
            np.stack([truth.x_mm[rows], truth.y_mm[rows]], 1), "unseen", out / "unseen_scatter.png")))
    verdict, verdict_lines = _verdict_lines(bundle, unseen)
    lines += verdict_lines
    if repeat is not None:
        figures.append(("Repeatability", _repeatability_figure(plt, bundle, repeat, out / "repeatability.png")))
    if "report/width_measured" in arrays and corrector.width is not None:
        figures.append(("Width calibration", _width_figure(plt, arrays, corrector.width, out / "width_fit.png")))
        lines += _fit_lines("Width calibration", bundle.extra_meta.get("width_fit") or {}, "form")
    depth_fit = bundle.extra_meta.get("depth_fit")
    if depth_fit:
        lines += _fit_lines("Depth calibration", depth_fit, "feature")
    shapes_fit = bundle.extra_meta.get("shapes_fit")
    if shapes_fit:
        figures.append(("Shape classification (held-out presses)",
                        _confusion_figure(plt, shapes_fit, out / "confusion.png")))
        lines += _shape_lines(shapes_fit)
    if "report/shape_hu" in arrays:
        figures.append(("Hu features", _hu_figure(plt, arrays, out / "hu_scatter.png")))
    lines.append("")
    for title, file in figures:
        lines += [f"## {title}", "", f"![{title}]({file})", ""]
    index = out / "index.md"
    write_file_atomic(index, "\n".join(lines))
    return WrittenReport(index, verdict)


def _verdict_lines(bundle: CalibrationBundle, unseen: Path | None) -> tuple[Verdict, list[str]]:
    """The verdict, and its section: from the unseen presses when given, else from the bundle alone."""
    from optitac_edge.calibration.verdict import Verdict, bundle_checks, judge, model_checks

    if unseen is not None:
        verdict = judge(bundle, *_measure_truth(unseen, bundle, corrected=True))
        basis = f"the presses of `{Path(unseen).name}`"
    else:
        verdict = Verdict(tuple(bundle_checks(bundle) + model_checks(bundle)))
        basis = "the bundle alone (give --unseen REC for the centroid and detection checks)"
    head, *checks = verdict.lines()
    return verdict, ["", "## Verdict", "", f"**{head[len('verdict: '):]}**, from {basis}:", "",
                     *(f"* {c.strip()}" for c in checks), ""]


def _repeatability_figure(plt: Any, bundle: CalibrationBundle, repeat: Path, path: Path) -> str:
    """Each position's calibrated centroid error, mean and range over its presses."""
    from optitac_edge.calibration.evaluation import repeatability

    positions = repeatability(*_measure_truth(repeat, bundle, corrected=True), bundle.layout.pitch_mm)
    fig, ax = plt.subplots(figsize=(7, 4), constrained_layout=True)
    k = np.arange(len(positions))
    for off, axis, colour in ((-0.12, "x", "tab:blue"), (0.12, "y", "tab:orange")):
        mean = np.array([getattr(p, f"mean_error_{axis}") for p in positions])
        rng = np.array([getattr(p, f"range_{axis}") for p in positions])
        ax.errorbar(k + off, mean, yerr=rng / 2, fmt="o", capsize=4, color=colour, label=f"{axis} error ± range/2")
    ax.axhline(0, color="gray", lw=0.5)
    ax.set_xticks(k, [f"({p.x_mm:.1f}, {p.y_mm:.1f})" for p in positions], fontsize=8)
    ax.set_ylabel("calibrated centroid error (mm)")
    ax.set_title("Repeatability: 10 presses per position")
    ax.legend()
    _save(plt, fig, path)
    return path.name


def _width_figure(plt: Any, arrays: Mapping[str, np.ndarray], w: WidthModel, path: Path) -> str:
    """The width model of each axis over the calibration presses' measured and true widths."""
    measured, true = arrays["report/width_measured"], arrays["report/width_true"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4), constrained_layout=True)
    xy = arrays.get("report/width_xy")
    xy = np.zeros((len(measured), 2)) if xy is None or len(xy) != len(measured) else xy
    calibrated = np.array([w.correct(a, b, x, y) for (a, b), (x, y) in zip(measured, xy)])
    for ax, col, axis, amap in zip(axes, (0, 1), ("major", "minor"), (w.major, w.minor)):
        ax.scatter(true, measured[:, col], s=10, label="measured FWHM")
        grid = np.linspace(min(measured[:, col].min(), amap.knots_measured[0]) * 0.95,
                           measured[:, col].max() * 1.05, 100)
        radial = w.radial_major if col == 0 else w.radial_minor
        ax.plot([amap(g) for g in grid], grid, "r-",
                label=f"{w.kind} width model" + (f" (at the centre; radial gain {radial:+.2f})" if radial else ""))
        fitted = calibrated[:, col]
        ax.scatter(true, fitted, s=10, marker="x", c="k", label="calibrated")
        ax.plot([0, true.max()], [0, true.max()], "k:", lw=0.8)
        rmse = float(np.sqrt(np.mean((fitted - true) ** 2)))
        ax.set_title(f"{axis} axis: calibrated RMSE {rmse:.3f} mm (calibration data)")
        ax.set_xlabel("true diameter (mm)")
        ax.set_ylabel("width (mm)")
        ax.legend(fontsize=7)
    _save(plt, fig, path)
    return path.name


def _chosen_holdout(shapes_fit: dict[str, Any]) -> dict[str, Any]:
    return next(shapes_fit[k] for k in ("unsupervised", "supervised")
                if shapes_fit[k]["kind"] == shapes_fit["kind"])["holdout"]


def _confusion_figure(plt: Any, shapes_fit: dict[str, Any], path: Path) -> str:
    """The chosen shape classifier's held-out confusion, row-normalised."""
    classes = shapes_fit["class_names"]
    conf = np.asarray(_chosen_holdout(shapes_fit)["confusion"], dtype=float)
    conf = conf / np.maximum(conf.sum(axis=1, keepdims=True), 1)
    fig, ax = plt.subplots(figsize=(5.5, 4.8), constrained_layout=True)
    ax.imshow(conf, cmap="Blues", vmin=0, vmax=1)
    for i in range(len(classes)):
        for j in range(len(classes)):
            ax.text(j, i, f"{conf[i, j]:.2f}", ha="center", va="center",
                    color="white" if conf[i, j] > 0.5 else "black")
    ax.set_xticks(range(len(classes)), classes, rotation=30)
    ax.set_yticks(range(len(classes)), classes)
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    ax.set_title(f"Held-out confusion ({shapes_fit['kind']} {shapes_fit['subset']})", fontsize=9)
    _save(plt, fig, path)
    return path.name


def _shape_lines(shapes_fit: dict[str, Any]) -> list[str]:
    """The shape classifier's choice and every Hu subset's held-out score, both kinds."""
    chosen = (f"Shape classifier: {shapes_fit['kind']} mixture on {shapes_fit['subset']}, held-out "
              f"average diagonal {_chosen_holdout(shapes_fit)['average_diagonal']:.3f}; paper's unsupervised GMM "
              f"{shapes_fit['unsupervised']['holdout']['average_diagonal']:.3f} "
              f"({shapes_fit['unsupervised']['selected']}), supervised "
              f"{shapes_fit['supervised']['holdout']['average_diagonal']:.3f} "
              f"({shapes_fit['supervised']['selected']})")
    lines = [chosen, "", "| Hu subset | unsupervised held-out avg. diagonal | supervised |", "|---|---|---|"]
    for name, res in shapes_fit["unsupervised"]["subsets"].items():
        sup = shapes_fit["supervised"]["subsets"].get(name, {}).get("holdout", {})
        lines.append(f"| {name} | {res['holdout']['average_diagonal']:.3f} | "
                     f"{sup.get('average_diagonal', float('nan')):.3f} |")
    return lines


def _hu_figure(plt: Any, arrays: Mapping[str, np.ndarray], path: Path) -> str:
    """Hu moments M1-M3 of the calibration presses, pairwise, by shape."""
    hu, label = arrays["report/shape_hu"], arrays["report/shape_label"]
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.4), constrained_layout=True)
    for ax, (a, b) in zip(axes, ((0, 1), (0, 2), (1, 2))):
        for kind, s in enumerate(SHAPES):
            sel = label == kind
            if sel.any():
                ax.scatter(hu[sel, a], hu[sel, b], s=8, c=_COLOURS[s], label=s)
        ax.set_xlabel(f"M{a + 1} (log)")
        ax.set_ylabel(f"M{b + 1} (log)")
    axes[0].legend(fontsize=7)
    fig.suptitle("Hu moments M1–M3 of the calibration presses")
    _save(plt, fig, path)
    return path.name


def _save(plt: Any, fig: Any, path: Path) -> None:
    """A figure as a PNG file, written all or nothing."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    write_file_atomic(path, buf.getvalue())
