"""The calibration steps after ``calibrate fibers``: orientation, levels, centroid, width, shapes, depth.

Each step replays recordings with known truth through the raw pipeline
(each recording with its own baseline: its rest frames and tare points; several
recordings -- days, sessions -- are measured each on its own and joined,
:func:`~optitac_edge.calibration.measure.measure_sessions`), fits its model,
and returns an updated bundle; the CLI saves it atomically. The fitted data are kept in the bundle
(``report/*`` arrays) so ``optitac-edge report`` can draw them later.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from optitac_edge.calibration.bundle_models import (
    with_centroid_map,
    with_depth_model,
    with_shape_model,
    with_width_model,
)
from optitac_edge.calibration.centroid_fit import FILLS, choose_fill, fit_centroid_map
from optitac_edge.calibration.contact_count import one_contact_evidence
from optitac_edge.calibration.depth_fit import RESPONSE_DRIFT, Presses, grouped_means, select_feature
from optitac_edge.calibration.evaluation import detected_rows, press_ids
from optitac_edge.calibration.levels_fit import (
    HeldOutLevels,
    choose_level,
    excursion_of,
    fiber_drift,
    frame_statistic,
    held_out_levels,
    rest_runs,
    spread,
)
from optitac_edge.calibration.measure import Measurements, fiber_signals, measure_sessions, recordings_named
from optitac_edge.calibration.orientation import (
    OrientationFit,
    fit_orientation,
    is_verified,
    layout_symmetries,
    mark_verified,
    reorient_bundle,
)
from optitac_edge.calibration.width_fit import WIDTH_FORMS, select_width_form
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.colour import COLOUR_MIXES
from optitac_edge.core.depth_model import DEPTH_FEATURES, DepthForceModel, depth_feature
from optitac_edge.core.levels import DRIFT_KEY, LEVELS_KEY, NOISE_KEY, fiber_excess
from optitac_edge.core.support import neighbour_table
from optitac_edge.errors import OrientationError, RecordingError
from optitac_edge.io.recording import SHAPES, Recording, Truth

log = logging.getLogger(__name__)
#: The centroid maps reach this far beyond the outermost fiber, pitches (3 mm on the paper's 1.5 mm array).
MAP_MARGIN_PITCH = 2.0


#: One recording, or several (days, sessions) calibrated from together.
Recordings = Recording | Sequence[Recording]


def _listed(recs: Recordings) -> tuple[Recording, ...]:
    return (recs,) if isinstance(recs, Recording) else tuple(recs)


def _measured(recs: Recordings, bundle: CalibrationBundle) -> tuple[Measurements, Truth, str]:
    """The raw pipeline's measurements of ``recs``, their truth and their names (for the lines)."""
    listed = _listed(recs)
    for rec in listed:
        if rec.truth is None:
            raise RecordingError(f"{rec.path}: calibration needs truth.csv")
    m, truth = measure_sessions(listed, bundle, corrected=False)
    return m, truth, recordings_named(listed)


def _with_report_arrays(bundle: CalibrationBundle, **arrays: np.ndarray) -> CalibrationBundle:
    extra = dict(bundle.extra_arrays)
    extra.update({f"report/{k}": np.asarray(v) for k, v in arrays.items()})
    return bundle.with_updates(extra_arrays=extra)


def press_orientation(m: Measurements, truth: Truth, bundle: CalibrationBundle) -> OrientationFit:
    """Which symmetry of the layout the bundle's fiber map is off by, from a recording's detected presses.

    Each press counts once: the mean raw centroid of its detected frames against its true position.
    """
    ids = press_ids(truth)
    rows = detected_rows(m, truth)
    measured, true = [], []
    for p in range(int(ids.max(initial=-1)) + 1):
        sel = np.flatnonzero((ids == p) & rows)
        if sel.size:
            frames = truth.frame[sel]
            measured.append((np.mean(m.x_mm[frames]), np.mean(m.y_mm[frames])))
            true.append((truth.x_mm[sel[0]], truth.y_mm[sel[0]]))
    return fit_orientation(np.array(measured).reshape(-1, 2), np.array(true).reshape(-1, 2),
                           layout_symmetries(bundle.layout), bundle.layout.pitch_mm)


@dataclass(frozen=True, eq=False)
class _Oriented:
    """The presses' orientation fit, from the reading that places them better: as configured or, with several
    contacts a frame, as one (``one``: those measurements; None when the bundle reads one already)."""

    fit: OrientationFit
    one: Measurements | None
    by_one: bool


def _oriented(recs: Recordings, bundle: CalibrationBundle, m: Measurements, truth: Truth) -> _Oriented:
    """A real skin's press can split into pieces that several contacts a frame report apart
    (:mod:`~optitac_edge.calibration.contact_count`): the orientation is fitted to the presses read both
    ways, and the fit that accepts an orientation with the smaller error is taken (either, on a sensor whose
    presses do not split)."""
    fit = press_orientation(m, truth, bundle)
    if bundle.options.max_contacts == 1:
        return _Oriented(fit, None, False)
    one = measure_sessions(_listed(recs), _one_contact(bundle), corrected=False)[0]
    fit_one = press_orientation(one, truth, bundle)
    by_one = (fit_one.symmetry is not None, -fit_one.best_rmse_mm) > (fit.symmetry is not None, -fit.best_rmse_mm)
    return _Oriented(fit_one if by_one else fit, one, by_one)


def _one_contact(bundle: CalibrationBundle) -> CalibrationBundle:
    return bundle.with_updates(options=replace(bundle.options, max_contacts=1))


def calibrate_orientation(recs: Recordings, bundle: CalibrationBundle
                          ) -> tuple[CalibrationBundle, OrientationFit]:
    """Check the bundle's fiber map against the recordings' presses; correct it if off by a symmetry.

    The presses are read as configured and, with several contacts a frame, as one (:func:`_oriented`).

    Raises
    ------
    OrientationError
        When the presses cannot tell the layout's symmetries apart, or none fits.
    """
    m, truth, where = _measured(recs, bundle)
    oriented = _oriented(recs, bundle, m, truth)
    fit = oriented.fit
    if fit.symmetry is None:
        raise OrientationError(f"{where}: {fit.reason}")
    names = ", ".join(r.path.name for r in _listed(recs))
    read = ", read as one contact a frame" if oriented.by_one else ""
    evidence = f"{fit.presses} presses of {names}{read}, RMS {fit.best_rmse_mm:.2f} mm"
    return reorient_bundle(bundle, fit.symmetry, evidence), fit


def calibrate_levels(recs: Recordings, bundle: CalibrationBundle) -> tuple[CalibrationBundle, dict[str, Any]]:
    """The contact levels, each fiber's band and (RGB frames) the colour mix, from the recordings' own rest and
    contact frames.

    Each fiber's drift since the baseline (its rest excursion over every rest frame of the recordings beyond
    what its frame-to-frame noise explains) gives, with the noise, its band (:mod:`optitac_edge.core.levels`);
    the on level is chosen where the rest and contact frames are best told apart
    (:func:`~optitac_edge.calibration.levels_fit.choose_level`), and how that choice does on frames it was not
    made on is measured fold by fold (whole presses and runs of rest frames held out,
    :func:`~optitac_edge.calibration.levels_fit.held_out_levels`). Neighbour support
    (:mod:`optitac_edge.core.support`) and, with RGB frames, every colour mix
    (:data:`~optitac_edge.core.colour.COLOUR_MIXES`) are tried the same way, and adopted only where their
    held-out error (missed contact frames plus false contacts, as fractions) is lower than luma's without
    support. The rest-frame noise of ``calibrate fibers`` stays the fallback of a bundle this step never saw.

    Raises
    ------
    RecordingError
        Without truth, or with too few rest or contact frames to choose on held-out ones.
    """
    listed = _listed(recs)
    where = recordings_named(listed)
    mixes = COLOUR_MIXES if bundle.fibers.pixel_format == "rgb" else {"luma": COLOUR_MIXES["luma"]}
    table = neighbour_table(bundle.layout)
    tried: dict[tuple[str, bool], _MixLevels] = {}
    for mix in mixes:
        signals = _mix_signals(listed, bundle, mix, where)
        for support in (False, True):
            tried[mix, support] = _levels_of(signals, bundle, where, table if support else None)
    errors = {key: (1.0 - t.held.detection) + t.held.false_rate for key, t in tried.items()}
    # the least held-out error; on a tie the most room between the held-out frames, then luma, then no support;
    # and no choice that places the calibration presses worse than luma without support (detection is not
    # bought with location: a colour mix moves every contact's moments, not only its detection)
    ranked = sorted(tried, key=lambda key: (round(errors[key], 9), -round(tried[key].held.margin, 3),
                                            key[0] != "luma", key[1]))
    plain = ("luma", False)
    located = {plain: _location_rms(listed, _with_levels(bundle, plain, tried[plain]))}
    best = plain
    for key in ranked:
        if key == plain:
            break
        located[key] = _location_rms(listed, _with_levels(bundle, key, tried[key]))
        if located[key] <= LOCATION_TOLERANCE * located[plain]:
            best = key
            break
    chosen = tried[best]
    summary = _levels_summary(chosen)
    summary["support"] = best[1]
    summary["heldout_error"] = {f"{mix}{' support' if support else ''}": round(e, 4)
                                for (mix, support), e in errors.items()}
    summary["heldout_margin"] = round(chosen.held.margin, 3)
    summary["location_rms_mm"] = {f"{mix}{' support' if support else ''}": round(v, 3)
                                  for (mix, support), v in located.items()}
    if len(mixes) > 1:
        summary["colour_mix"] = best[0]
    levelled = _with_levels(bundle, best, chosen)
    meta = {**levelled.extra_meta[LEVELS_KEY], **summary}
    return levelled.with_updates(extra_meta={**levelled.extra_meta, LEVELS_KEY: meta}), summary


#: calibrate levels adopts a colour mix or neighbour support only where the calibration presses' location (RMS
#: under their best symmetry) stays within this factor of luma's without support.
LOCATION_TOLERANCE = 1.1


def _with_levels(bundle: CalibrationBundle, key: tuple[str, bool], m: _MixLevels) -> CalibrationBundle:
    """The bundle with the levels ``m`` of colour mix and support ``key``."""
    options = replace(bundle.options, on_level=m.level, colour_mix=key[0], support=key[1])
    meta = {**bundle.extra_meta.get(LEVELS_KEY, {}), "drift_samples": m.rest_frames}
    arrays = {**bundle.extra_arrays, DRIFT_KEY: m.drift.astype(np.float32)}
    return bundle.with_updates(options=options, extra_arrays=arrays,
                               extra_meta={**bundle.extra_meta, LEVELS_KEY: meta})


def _location_rms(recs: tuple[Recording, ...], bundle: CalibrationBundle) -> float:
    """The recordings' presses as ``bundle`` places them: RMS error under their best symmetry, mm (inf: none
    detected)."""
    m, truth = measure_sessions(recs, bundle, corrected=False)
    fit = press_orientation(m, truth, bundle)
    return fit.best_rmse_mm if fit.presses else math.inf


@dataclass(frozen=True, eq=False)
class _MixLevels:
    """What one colour mix gives: the level, each fiber's drift and excursion, the held-out figures."""

    level: float
    drift: np.ndarray
    excursion: np.ndarray
    banded: int
    held: HeldOutLevels
    rest_frames: int
    live: np.ndarray


@dataclass(frozen=True, eq=False)
class _Signals:
    """The recordings' scored frames read through one colour mix: each fiber's signal and light, what they
    are, their groups for the folds, the expected squared noise."""

    signals: np.ndarray
    contact: np.ndarray
    groups: np.ndarray
    noise_part: np.ndarray | None
    live: np.ndarray


def _mix_signals(recs: tuple[Recording, ...], bundle: CalibrationBundle, mix: str, where: str) -> _Signals:
    """The frames the recordings give read through colour mix ``mix`` (no band, no support)."""
    bundle = bundle.with_updates(options=replace(bundle.options, colour_mix=mix, support=False))
    signals, light, truth, t_ns = fiber_signals(recs, bundle)
    ok = np.all(np.isfinite(signals), axis=1)
    sessions = np.zeros(len(truth), dtype=np.int64) if truth.session is None else truth.session
    contact = truth.contact[ok]
    signals, light = signals[ok], light[ok]
    noise = bundle.extra_arrays.get(NOISE_KEY)
    part = (None if noise is None else
            np.square(np.asarray(noise, dtype=np.float64) / light) * (1.0 + 1.0 / bundle.baseline_frames))
    runs = rest_runs(contact, sessions[ok], truth.frame[ok], t_ns[ok], round(bundle.options.gap_s * 1e9))
    if contact.all() or not contact.any():
        raise RecordingError(f"{where}: choosing levels needs rest frames and contact frames in the truth")
    return _Signals(signals, contact, np.where(contact, press_ids(truth)[ok], runs), part,
                    ~np.asarray(bundle.fibers.dead, dtype=bool))


def _levels_of(f: _Signals, bundle: CalibrationBundle, where: str, support: np.ndarray | None) -> _MixLevels:
    """The levels of frames ``f``, with neighbour support (``support``: the neighbour table) or without."""
    contact, live = f.contact, f.live
    try:
        held = held_out_levels(f.signals, f.noise_part, contact, f.groups, live, support=support)
    except ValueError as exc:
        raise RecordingError(f"{where}: {exc}") from None
    rest_part = None if f.noise_part is None else f.noise_part[~contact]
    drift = fiber_drift(f.signals[~contact], rest_part)
    excursion = excursion_of(drift, rest_part)
    excess = fiber_excess(excursion, live, int((~contact).sum()))
    z = frame_statistic(f.signals, excess, live, support)
    level = choose_level(z[~contact], z[contact])
    return _MixLevels(level, drift, excursion, 0 if excess is None else int(np.count_nonzero(excess)), held,
                      int((~contact).sum()), live)


def _levels_summary(m: _MixLevels) -> dict[str, Any]:
    held = m.held
    return {"on_level": round(m.level, 5), "heldout_detection": round(held.detection, 4),
            "heldout_false_contacts": round(held.false_rate, 4), "contact_frames": held.contact_frames,
            "rest_frames": held.rest_frames, "folds": held.folds,
            "fold_levels": spread(np.array(held.levels)), "rest_excursion": spread(m.excursion[m.live]),
            "drift": spread(m.drift[m.live]), "banded_fibers": m.banded}


def calibrate_centroid(recs: Recordings, bundle: CalibrationBundle, fill: str = "auto",
                       bundle_path: str = "CAL", contacts: str = "auto") -> tuple[CalibrationBundle, dict[str, Any]]:
    """The paper's centroid error maps from presses of known position (``fill``: see fit_centroid_map;
    ``auto``, default: :func:`~optitac_edge.calibration.centroid_fit.choose_fill` on presses held out of the map).

    ``contacts``: ``auto`` (default) reads the presses as one contact a frame instead of the configured
    several where that places them better (:func:`one_contact_evidence`), ``keep`` keeps the configured count.

    The bundle's orientation is checked against the same presses first.

    Raises
    ------
    OrientationError
        If the presses show the fiber map off by a symmetry of the layout, or
        cannot confirm an orientation that was never verified.
    """
    m, truth, where = _measured(recs, bundle)
    oriented = _oriented(recs, bundle, m, truth)
    fit = oriented.fit
    fix = (f"fix it with: optitac-edge calibrate orientation {' '.join(str(r.path) for r in _listed(recs))} "
           f"--cal {bundle_path}")
    if fit.symmetry is not None and not fit.symmetry.is_identity:
        raise OrientationError(
            f"{where}: the bundle's fiber map is {fit.symmetry.label} from these presses "
            f"(RMS {fit.best_rmse_mm:.2f} mm that way, {fit.rmse_mm[0]:.2f} mm as it is); {fix}")
    if fit.symmetry is None and not is_verified(bundle):
        raise OrientationError(f"{where}: cannot confirm the bundle's orientation: {fit.reason}; "
                               "verify it with 'optitac-edge orient' or 'calibrate orientation' on other presses")
    contact_summary: dict[str, Any] = {}
    if contacts == "auto" and oriented.one is not None:
        evidence = one_contact_evidence(m, oriented.one, truth)
        contact_summary = {"max_contacts": 1 if evidence.adopt else bundle.options.max_contacts,
                           "rms_mm_several": round(evidence.several_rms_mm, 3),
                           "rms_mm_one": round(evidence.one_rms_mm, 3)}
        if evidence.adopt:
            bundle, m = _one_contact(bundle), oriented.one
    rows = np.flatnonzero(detected_rows(m, truth))
    if rows.size < 3:
        raise RecordingError(f"{where}: only {rows.size} detected presses to calibrate the centroid")
    frames = truth.frame[rows]
    measured = np.stack([m.x_mm[frames], m.y_mm[frames]], axis=1)
    true = np.stack([truth.x_mm[rows], truth.y_mm[rows]], axis=1)
    span = bundle.layout.radius_mm + MAP_MARGIN_PITCH * bundle.layout.pitch_mm
    groups = press_ids(truth)[rows]
    try:
        chosen, candidates = choose_fill(measured, true, groups, span, FILLS if fill == "auto" else (fill,))
    except ValueError as exc:
        raise RecordingError(f"{where}: {exc}") from None
    fill = chosen["fill"]
    error_map = fit_centroid_map(measured, true, half_span_mm=span, fill=fill)
    corrected = np.array([error_map.correct(x, y) for x, y in measured])
    summary = {
        "frames": int(rows.size), "presses": int(np.unique(groups).size), "fill": fill,
        "raw_rmse_mm": np.sqrt(np.mean((measured - true) ** 2, axis=0)).round(4).tolist(),
        "fitted_rmse_mm": np.sqrt(np.mean((corrected - true) ** 2, axis=0)).round(4).tolist(),
        "heldout_rmse_mm": chosen["heldout_rmse_mm"], "heldout_spread_mm": chosen["heldout_spread_mm"],
        **contact_summary,
    }
    if fit.symmetry is not None:
        names = ", ".join(r.path.name for r in _listed(recs))
        bundle = mark_verified(bundle, f"{fit.presses} presses of {names}, RMS {fit.best_rmse_mm:.2f} mm")
    bundle = with_centroid_map(bundle, error_map)
    bundle = _with_report_arrays(bundle, centroid_measured=measured, centroid_true=true)
    details = {**summary, "candidates": candidates}
    return bundle.with_updates(extra_meta={**bundle.extra_meta, "centroid_fit": details}), summary


def calibrate_width(recs: Recordings, bundle: CalibrationBundle, kind: str = "auto"
                    ) -> tuple[CalibrationBundle, dict[str, Any]]:
    """Per-axis width model from circular presses of known diameter.

    ``kind``: ``auto`` (default) chooses among :data:`~optitac_edge.calibration.width_fit.WIDTH_FORMS` by
    presses held out of the fit; a form's name fits that form (its held-out figures are still reported;
    ``linear``: the paper's).
    """
    m, truth, where = _measured(recs, bundle)
    rows = np.flatnonzero(detected_rows(m, truth) & (truth.shape == "circle"))
    if rows.size < 2 or np.unique(truth.size_mm[rows]).size < 2:
        raise RecordingError(f"{where}: width calibration needs circles of at least two diameters")
    frames = truth.frame[rows]
    major, minor, true = m.major_mm[frames], m.minor_mm[frames], truth.size_mm[rows]
    radius = float(bundle.layout.radius_mm)
    rho2 = (m.x_mm[frames] ** 2 + m.y_mm[frames] ** 2) / radius ** 2
    forms = WIDTH_FORMS if kind == "auto" else (kind,)
    try:
        form, model, candidates = select_width_form(major, minor, rho2, true, press_ids(truth)[rows], radius,
                                                    forms)
    except ValueError as exc:
        raise RecordingError(f"{where}: {exc}") from None
    fitted = np.array([model.correct(a, b, x, y) for a, b, x, y in
                       zip(major, minor, m.x_mm[frames], m.y_mm[frames])])
    chosen = next(c for c in candidates if c["form"] == form)
    presses = press_ids(truth)[rows]
    per_diameter = min(np.unique(presses[true == d]).size for d in np.unique(true))
    summary = {
        "frames": int(rows.size), "presses": int(np.unique(presses).size), "presses_per_diameter": int(per_diameter),
        "kind": form,
        "fitted_rmse_mm": np.sqrt(np.mean((fitted - true[:, None]) ** 2, axis=0)).round(4).tolist(),
        "heldout_rmse_mm": chosen["heldout_rmse_mm"], "heldout_spread_mm": chosen["heldout_spread_mm"],
    }
    bundle = with_width_model(bundle, model)
    bundle = _with_report_arrays(bundle, width_measured=np.stack([major, minor], axis=1), width_true=true,
                                 width_xy=np.stack([m.x_mm[frames], m.y_mm[frames]], axis=1))
    details = {**summary, "candidates": candidates}
    return bundle.with_updates(extra_meta={**bundle.extra_meta, "width_fit": details}), summary


def calibrate_shapes(recs: Recordings, bundle: CalibrationBundle, seed: int = 0
                     ) -> tuple[CalibrationBundle, dict[str, Any]]:
    """Shape classifier from labelled presses (the paper's GMM search and a supervised alternative)."""
    from optitac_edge.calibration.shape_fit import ShapeFitSettings, fit_shape_model

    m, truth, where = _measured(recs, bundle)
    rows = np.flatnonzero(detected_rows(m, truth))
    labels = truth.shape[rows]
    if np.unique(labels).size < 2:
        raise RecordingError(f"{where}: shape calibration needs presses of at least two shapes")
    features = m.features[truth.frame[rows]]
    report = fit_shape_model(features, labels, press_ids(truth)[rows], ShapeFitSettings(seed=seed))
    bundle = with_shape_model(bundle, report.model)
    details = report.to_dict()
    summary = {
        "chosen": f"{report.kind} {details['subset']}",
        "holdout_average_diagonal": round(details["holdout_average_diagonal"], 4),
        **{f"{kind}_holdout_average_diagonal": round(details[kind]["holdout"]["average_diagonal"] or 0.0, 4)
           for kind in ("unsupervised", "supervised")},
        "train_presses_frames": details["n_train"], "holdout_frames": details["n_test"],
    }
    bundle = _with_report_arrays(bundle, shape_hu=features[:, :7],
                                 shape_label=np.array([SHAPES.index(s) for s in labels], dtype=np.int64))
    return bundle.with_updates(extra_meta={**bundle.extra_meta, "shapes_fit": details}), summary


@dataclass(frozen=True, eq=False)
class DepthPresses:
    """A recording's detected presses of known depth, each the mean of its detected frames.

    Attributes
    ----------
    features : dict of str to ndarray, shape (P,)
        Each asked feature (:data:`~optitac_edge.core.depth_model.DEPTH_FEATURES`) per press.
    rho2 : ndarray, shape (P,)
        Squared radius over the array's squared radius (not capped).
    level : ndarray, shape (P,)
        The commanded depth, mm.
    force : ndarray, shape (P,)
        The load cell's force, N (NaN without one).
    frames : ndarray, shape (P,), int
        Detected frames per press.
    with_force : bool
        Every detected frame has a load cell's force.
    session : ndarray, shape (P,), int
        The recording (session) of each press, numbered in the order given.
    """

    features: dict[str, np.ndarray]
    rho2: np.ndarray
    level: np.ndarray
    force: np.ndarray
    frames: np.ndarray
    with_force: bool
    session: np.ndarray


def depth_presses(recs: Recordings, bundle: CalibrationBundle, names: tuple[str, ...] = DEPTH_FEATURES
                  ) -> DepthPresses:
    """The raw pipeline's presses of ``recs`` (``depths`` recordings) with the features ``names``.

    Raises
    ------
    RecordingError
        Without truth, or with detected presses at fewer than 3 depths.
    """
    m, truth, where = _measured(recs, bundle)
    rows = np.flatnonzero(detected_rows(m, truth))
    if np.unique(truth.depth_mm[rows]).size < 3:
        raise RecordingError(f"{where}: depth calibration needs detected presses at 3 depths or more "
                             f"(the 'depths' experiment), got {np.unique(truth.depth_mm[rows]).size}")
    frames = truth.frame[rows]
    rho2 = (m.x_mm[frames] ** 2 + m.y_mm[frames] ** 2) / float(bundle.layout.radius_mm) ** 2
    force = truth.force_n[rows] if truth.force_n is not None else np.full(rows.size, np.nan)
    session = np.zeros(rows.size) if truth.session is None else truth.session[rows].astype(np.float64)
    values = np.stack([depth_feature(m, f)[frames] for f in names], axis=1)
    means, counts = grouped_means(np.concatenate([np.stack([rho2, truth.depth_mm[rows], force, session], axis=1),
                                                  values], axis=1), press_ids(truth)[rows])
    return DepthPresses({f: means[:, 4 + k] for k, f in enumerate(names)}, means[:, 0], means[:, 1], means[:, 2],
                        counts, bool(np.isfinite(force).all()), np.rint(means[:, 3]).astype(np.int64))


def calibrate_depth(recs: Recordings, bundle: CalibrationBundle, feature: str | None = None,
                    drift: float = RESPONSE_DRIFT) -> tuple[CalibrationBundle, dict[str, Any]]:
    """Depth model, and force model when ``truth.csv`` has a load cell's ``force_n``, from presses of known
    depth (the ``depths`` experiment: one indenter, several depths and positions).

    Each press counts once (the mean of its detected frames, :func:`depth_presses`). The model's input is
    chosen among :data:`~optitac_edge.core.depth_model.DEPTH_FEATURES` by presses held out of the fit
    (:func:`~optitac_edge.calibration.depth_fit.select_feature`), separately for depth and force; ``feature``
    fixes it instead (the held-out figures are still reported). From several recordings (days, sessions)
    that each press at 3 depths or more, every fold holds out a whole session, so the choice sees how the
    skin's response changed between them; from one, ``drift`` is the change between days it guards against.
    """
    p = depth_presses(recs, bundle, DEPTH_FEATURES if feature is None else (feature,))
    counts, level = p.frames, p.level
    radius = float(bundle.layout.radius_mm)
    groups = np.arange(counts.size)  # one row per press: a fold never splits a press
    try:
        depth = select_feature(p.features, Presses(p.rho2, level, level, counts, groups, p.session), radius, drift)
        force_sel = (select_feature(p.features, Presses(p.rho2, p.force, level, counts, groups, p.session), radius,
                                    drift) if p.with_force else None)
    except ValueError as exc:
        raise RecordingError(f"{recordings_named(_listed(recs))}: {exc}") from None
    model = DepthForceModel(depth.feature, depth.fit.model, None if force_sel is None else force_sel.fit.model,
                            "" if force_sel is None else force_sel.feature)
    chosen = depth.chosen
    summary: dict[str, Any] = {
        "presses": int(counts.size), "frames": int(counts.sum()), "feature": depth.feature,
        "heldout_by": (f"{depth.folds} sessions" if depth.by_session
                       else f"{depth.folds} folds of presses, response drift prior {drift:.0%}"),
        "depth_range_mm": [round(float(level.min()), 3), round(float(level.max()), 3)],
        "depth_radial": depth.fit.model.radial, "fitted_depth_rmse_mm": round(depth.fit.rmse, 4),
        "heldout_depth_rmse_mm": round(chosen.heldout_rmse, 4),
        "heldout_depth_spread_mm": round(chosen.heldout_spread, 4),
        "expected_depth_rmse_mm": round(chosen.expected_rmse, 4)}
    details: dict[str, Any] = {**summary, "folds": depth.folds,
                               "folds_by": "session" if depth.by_session else "press",
                               "response_drift": None if depth.by_session else drift,
                               "depth_candidates": [c.to_dict() for c in depth.candidates]}
    if force_sel is not None:
        span = float(np.ptp(p.force))
        fc = force_sel.chosen
        force_summary = {
            "force_feature": force_sel.feature,
            "force_range_n": [round(float(p.force.min()), 3), round(float(p.force.max()), 3)],
            "force_radial": force_sel.fit.model.radial, "fitted_force_rmse_n": round(force_sel.fit.rmse, 4),
            "heldout_force_rmse_n": round(fc.heldout_rmse, 4),
            "heldout_force_rmse_pct_of_range": round(100 * fc.heldout_rmse / span, 2) if span else None}
        summary.update(force_summary)
        details.update(force_summary, force_candidates=[c.to_dict() for c in force_sel.candidates])
    bundle = with_depth_model(bundle, model)
    # per press: the chosen feature, rho^2, depth, and the force where a load cell measured it (finite values)
    presses = np.stack([p.features[depth.feature], p.rho2, level, p.force], axis=1)
    bundle = _with_report_arrays(bundle, depth_presses=presses if p.with_force else presses[:, :3],
                                 depth_press_frames=counts)
    return bundle.with_updates(extra_meta={**bundle.extra_meta, "depth_fit": details}), summary
