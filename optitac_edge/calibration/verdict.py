"""Is a calibration good enough? One verdict with its reasons (``evaluate`` and ``report`` print it).

The limits (docs/calibration.md, "What good looks like"):

=============================  ================================  ==========================================
check                          limit                             why
=============================  ================================  ==========================================
fiber map                      residual <= 0.15 pitch RMS,       a blob farther off is probably another
                               dead fibers <= 5 %                fiber, or the image is out of focus
orientation                    checked against presses           the 12 symmetries look alike at rest
coverage                       >= 90 % of the live fibers        the centroid map is extrapolated where
                               within one pitch of a press       no press was
centroid (evaluated presses)   RMSE <= 0.27 pitch per axis       the paper's unseen accuracy (0.4 mm
                                                                 on its 1.5 mm array)
detection (evaluated presses)  >= 99 % of contact frames,        a missed or invented contact reaches
                               0 false contacts                  the gripper
depth (when calibrated)        >= 56 presses; held-out and       below 56 presses the held-out error has
                               evaluated RMSE <= 1/6 pitch       not settled (the learning curve in
                               against commanded depths;         docs/accuracy.md); an evaluated error far
                               evaluated <= 2x held-out +        above the held-out one: the skin changed
                               1/30 pitch                        (0.25 and 0.05 mm on the paper's array: a
                                                                 skin and its pins scale with the array)
width (when calibrated)        >= 3 presses of each diameter;    below 3 a diameter the held-out error has
                               held-out and evaluated RMSE       not settled (docs/accuracy.md); 1/3 pitch
                               <= 1/3 pitch per axis; evaluated  (0.5 mm on the paper's array) is half the
                               <= 2x held-out + 1/15 pitch       paper's width accuracy
=============================  ================================  ==========================================
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from optitac_edge.calibration.evaluation import centroid_accuracy, depth_accuracy, detection, width_accuracy
from optitac_edge.calibration.measure import Measurements
from optitac_edge.calibration.orientation import is_verified
from optitac_edge.core.bundle import CalibrationBundle
from optitac_edge.core.corrections import CENTROID_KEY, DEPTH_KEY, WIDTH_KEY
from optitac_edge.core.levels import LEVELS_KEY
from optitac_edge.io.recording import Truth

MAX_RESIDUAL_PITCH = 0.15
MAX_DEAD_FRACTION = 0.05
MIN_COVERAGE = 0.90
#: Limits in pitches of the bundle's array (the paper's 1.5 mm array: 0.4 mm centroid, 0.25 mm depth,
#: 0.5 mm width, agreement slack 0.05 mm depth and 0.1 mm width).
MAX_CENTROID_RMSE_PITCH = 0.4 / 1.5
MIN_DETECTION = 0.99
#: Presses a depth model needs (the learning curve on the simulator's physics, docs/accuracy.md).
MIN_DEPTH_PRESSES = 56
MAX_DEPTH_RMSE_PITCH = 0.25 / 1.5
#: Presses of each diameter a width model needs (the learning curve, docs/accuracy.md).
MIN_WIDTH_PRESSES_PER_DIAMETER = 3
MAX_WIDTH_RMSE_PITCH = 0.5 / 1.5
#: An error evaluated on other presses above ``AGREEMENT * held-out + slack`` disagrees with the calibration's
#: own held-out figure (the slack, pitches: 0.05 mm for depth, 0.1 mm for width on the paper's array).
AGREEMENT, DEPTH_AGREEMENT_PITCH, WIDTH_AGREEMENT_PITCH = 2.0, 0.05 / 1.5, 0.1 / 1.5
#: Presses each experiment's model needs for its held-out error to settle: (model, what, how many presses at
#: the least; of each diameter for widths).
PRESSES_NEEDED = {"depths": ("depth", f"{MIN_DEPTH_PRESSES} presses", MIN_DEPTH_PRESSES),
                  "widths": ("width", f"{MIN_WIDTH_PRESSES_PER_DIAMETER} presses of each diameter",
                             MIN_WIDTH_PRESSES_PER_DIAMETER)}


@dataclass(frozen=True)
class Check:
    """One check of a verdict: its name, pass or fail, what was seen against what is required, and how many
    samples it saw (``n``; None: a check of the bundle itself). A check on zero samples is *not measured*:
    never ok, and said so (``[not measured]``), whatever ``ok`` was given."""

    name: str
    ok: bool
    seen: str
    fix: str = ""
    n: int | None = None

    def __post_init__(self) -> None:
        if self.n == 0 and self.ok:
            object.__setattr__(self, "ok", False)

    @property
    def measured(self) -> bool:
        return self.n is None or self.n > 0

    def line(self) -> str:
        mark = "ok" if self.ok else "FAIL" if self.measured else "not measured"
        return f"  [{mark}] {self.name}: {self.seen}" + ("" if self.ok else f" -> {self.fix}")


@dataclass(frozen=True)
class Verdict:
    checks: tuple[Check, ...]

    @property
    def good(self) -> bool:
        return all(c.ok for c in self.checks)

    def lines(self) -> list[str]:
        failed = [c.name for c in self.checks if not c.ok and c.measured]
        unmeasured = [c.name for c in self.checks if not c.measured]
        parts = [*failed, *(f"{name} not measured" for name in unmeasured)]
        head = ("verdict: GOOD ENOUGH (every check passes)" if not parts
                else f"verdict: NOT GOOD ENOUGH ({', '.join(parts)})")
        return [head, *(c.line() for c in self.checks)]


def coverage(bundle: CalibrationBundle) -> float | None:
    """Fraction of live fibers within one pitch of a press the centroid map was fitted to (None: no map)."""
    if CENTROID_KEY not in bundle.extra_meta or "report/centroid_true" not in bundle.extra_arrays:
        return None
    presses = np.asarray(bundle.extra_arrays["report/centroid_true"], dtype=np.float64).reshape(-1, 2)
    live = bundle.layout.xy_mm[~bundle.fibers.dead]
    if not len(presses) or not len(live):
        return 0.0
    d, _ = cKDTree(presses).query(live)
    return float(np.mean(d <= bundle.layout.pitch_mm + 1e-9))


def bundle_checks(bundle: CalibrationBundle) -> list[Check]:
    """The checks that need only the bundle: fiber map, orientation, coverage."""
    report = bundle.fiber_map_report
    pitch_px = bundle.transform.scale_px_per_mm * bundle.layout.pitch_mm
    residual = float(report.get("residual_rms_px", math.nan))
    dead = float(np.mean(bundle.fibers.dead))
    fiber_ok = residual <= MAX_RESIDUAL_PITCH * pitch_px and dead <= MAX_DEAD_FRACTION
    checks = [Check("fiber map", fiber_ok,
                    f"residual {residual:.2f} px = {residual / pitch_px:.2f} pitch (limit {MAX_RESIDUAL_PITCH}), "
                    f"{100 * dead:.1f} % dead (limit {100 * MAX_DEAD_FRACTION:g} %)",
                    "check focus and the LED in the view, then calibrate fibers again")]
    record = bundle.extra_meta.get("orientation", {})
    checks.append(Check("orientation", is_verified(bundle),
                        f"checked when it was set ({record.get('evidence', '')}: the raw centroid's error, before "
                        "any centroid calibration)" if is_verified(bundle) else "never checked",
                        "run 'calibrate orientation REC' on presses with truth, or 'optitac-edge orient'"))
    cov = coverage(bundle)
    checks.append(Check("coverage", cov is not None and cov >= MIN_COVERAGE,
                        "no centroid calibration" if cov is None else
                        f"{100 * cov:.0f} % of the live fibers within a pitch of a calibration press "
                        f"(limit {100 * MIN_COVERAGE:g} %)",
                        "calibrate the centroid from a 'seen' collection (a press over every fiber)"))
    return checks


def levels_line(bundle: CalibrationBundle) -> str:
    """The bundle's contact levels and how they were chosen, for a line a person reads."""
    o = bundle.options
    if not o.noise_levels:
        return f"levels: the paper's threshold ({bundle.thresholds.threshold:g} gray levels)"
    meta = bundle.extra_meta.get(LEVELS_KEY, {})
    if o.on_level > 0 and _numbers(meta.get("heldout_detection"), meta.get("heldout_false_contacts")):
        return (f"levels: on {o.on_level:.4f} (relative), chosen on {meta.get('contact_frames')} contact and "
                f"{meta.get('rest_frames')} rest frames; held out at calibration: detection "
                f"{100 * meta['heldout_detection']:.1f} %, false contacts {100 * meta['heldout_false_contacts']:.1f} %")
    return (f"levels: {o.k_on:g} x the rest frames' noise (each fiber's own beyond the typical one a band); "
            "'calibrate levels' on presses chooses them on held-out frames")


def judge(bundle: CalibrationBundle, m: Measurements, truth: Truth) -> Verdict:
    """The verdict on ``bundle`` from a recording of presses it was not calibrated on."""
    checks = bundle_checks(bundle)
    c = centroid_accuracy(m, truth)
    worst = max(c.rmse_x, c.rmse_y) if c.n else math.nan
    limit = MAX_CENTROID_RMSE_PITCH * bundle.layout.pitch_mm
    checks.append(Check("centroid", worst <= limit,
                        f"RMSE x {c.rmse_x:.3f}, y {c.rmse_y:.3f} mm over {c.n} frames of presses this bundle was not "
                        f"calibrated on (limit {limit:.3g} mm = {MAX_CENTROID_RMSE_PITCH:.2f} pitch)" if c.n
                        else "0 detected contact frames to measure it on",
                        "calibrate the centroid on presses that cover the array, then evaluate on others", n=c.n))
    d = detection(m, truth)
    rate = d.rate if d.contact_frames else math.nan
    checks.append(Check("detection", rate >= MIN_DETECTION,
                        f"{d.detected}/{d.contact_frames} contact frames (limit {100 * MIN_DETECTION:g} %); "
                        f"{levels_line(bundle).removeprefix('levels: ')}" if d.contact_frames
                        else "0 contact frames in the recording",
                        "check the LED and the rest frames; take the baseline again (tare)"
                        if d.contact_frames else "evaluate on a recording with presses", n=d.contact_frames))
    checks.append(Check("false contacts", d.false_contacts == 0,
                        f"{d.false_contacts} on {d.rest_frames} rest frames (limit 0)" if d.rest_frames
                        else "0 rest frames after the baseline in the recording",
                        "raise the contact level (calibrate levels on more rest frames), or tare" if d.rest_frames
                        else "evaluate on a recording with contact-free frames between its presses", n=d.rest_frames))
    checks += model_checks(bundle, m, truth)
    return Verdict(tuple(checks))


def model_checks(bundle: CalibrationBundle, m: Measurements | None = None, truth: Truth | None = None
                 ) -> list[Check]:
    """The width and depth models' checks, where the bundle has them."""
    return [c for c in (width_check(bundle, m, truth), depth_check(bundle, m, truth)) if c is not None]


def _numbers(*values: object) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def width_check(bundle: CalibrationBundle, m: Measurements | None = None, truth: Truth | None = None
                ) -> Check | None:
    """The width model's check (None: the bundle has none): presses of each diameter, its held-out error at
    calibration, and, when the evaluated recording presses circles of several diameters, the error there."""
    if WIDTH_KEY not in bundle.extra_meta:
        return None
    fit = bundle.extra_meta.get("width_fit", {})
    fix = "collect widths (every diameter, 5 presses each) and calibrate width again"
    heldout, per_diameter = fit.get("heldout_rmse_mm"), fit.get("presses_per_diameter")
    if not (isinstance(heldout, list) and len(heldout) == 2 and _numbers(*heldout, per_diameter)):
        return Check("width", False, "calibrated without held-out presses (an older calibration)", fix)
    worst = max(heldout)
    seen = (f"{per_diameter} presses of its rarest diameter (need {MIN_WIDTH_PRESSES_PER_DIAMETER}), held-out "
            f"RMSE {heldout[0]:.3f} / {heldout[1]:.3f} mm at calibration")
    pitch = bundle.layout.pitch_mm
    limit = MAX_WIDTH_RMSE_PITCH * pitch
    ok = per_diameter >= MIN_WIDTH_PRESSES_PER_DIAMETER and worst <= limit
    report = width_accuracy(m, truth, bundle.layout.pitch_mm) if m is not None and truth is not None else None
    here = None if report is None else (
        max(report.rmse_major, report.rmse_minor),
        f"{report.rmse_major:.3f} / {report.rmse_minor:.3f} mm here over {report.n} frames")
    return _model_check(Check("width", ok, seen, fix), worst, here, (limit, WIDTH_AGREEMENT_PITCH * pitch),
                        f"limit {limit:.3g} mm = {MAX_WIDTH_RMSE_PITCH:.2f} pitch")


def depth_check(bundle: CalibrationBundle, m: Measurements | None = None, truth: Truth | None = None
                ) -> Check | None:
    """The depth model's check (None: the bundle has none): enough presses, its held-out error at calibration,
    and, when the evaluated recording presses at several depths, the error measured there agreeing with it."""
    if DEPTH_KEY not in bundle.extra_meta:
        return None
    fit = bundle.extra_meta.get("depth_fit", {})
    fix = "collect depths (every point at every depth) and calibrate depth again"
    heldout, presses = fit.get("heldout_depth_rmse_mm"), fit.get("presses", 0)
    spread = fit.get("heldout_depth_spread_mm", math.nan)
    if not _numbers(heldout, presses, spread):
        return Check("depth", False, "calibrated without held-out presses (an older calibration)", fix)
    seen = (f"{presses} presses (need {MIN_DEPTH_PRESSES}), held-out RMSE {heldout:.3f} "
            f"± {spread:.3f} mm at calibration")
    pitch = bundle.layout.pitch_mm
    limit = MAX_DEPTH_RMSE_PITCH * pitch
    ok = presses >= MIN_DEPTH_PRESSES and heldout <= limit
    report = depth_accuracy(m, truth) if m is not None and truth is not None else None
    here = None if report is None else (report.depth_rmse_mm,
                                        f"{report.depth_rmse_mm:.3f} mm here over {report.n} frames")
    return _model_check(Check("depth", ok, seen, fix), heldout, here, (limit, DEPTH_AGREEMENT_PITCH * pitch),
                        f"limit {limit:.3g} mm = {MAX_DEPTH_RMSE_PITCH:.2f} pitch against commanded depths")


def _model_check(calibrated: Check, heldout: float, here: tuple[float, str] | None, limits: tuple[float, float],
                 limit_text: str) -> Check:
    """A model's check from its calibration figures (``calibrated``) and, when the evaluated recording
    measured it, the error there (``here``: value, words): within ``limits[0]`` and agreeing with ``heldout``
    (within :data:`AGREEMENT` times it plus ``limits[1]`` mm)."""
    ok, seen, fix = calibrated.ok, calibrated.seen, calibrated.fix
    if here is not None:
        limit, slack_mm = limits
        value, words = here
        agrees = value <= AGREEMENT * heldout + slack_mm
        seen += f", {words}"
        ok = ok and value <= limit and agrees
        if not agrees:
            fix = "the skin responds differently than when calibrated: " + fix
    return Check(calibrated.name, ok, f"{seen} ({limit_text})", fix)
