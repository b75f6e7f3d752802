"""One contact a frame or several: chosen on the calibration presses, kept where they show no difference."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from optitac_edge.calibration.contact_count import one_contact_evidence
from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.calibration.steps import calibrate_centroid
from optitac_edge.io.recording import Recording, Truth
from optitac_edge.sim.scenarios import write_scenario

PITCH = 4.0


def _truth(xy: np.ndarray, frames_per_press: int = 2) -> Truth:
    xy = np.repeat(xy, frames_per_press, axis=0)
    n = len(xy)
    return Truth(frame=np.arange(n), contact=np.ones(n, bool), shape=np.full(n, "circle"), x_mm=xy[:, 0],
                 y_mm=xy[:, 1], angle_deg=np.full(n, np.nan), size_mm=np.full(n, 10.0), depth_mm=np.ones(n))


def _read(xy: np.ndarray) -> SimpleNamespace:
    return SimpleNamespace(contact=np.ones(len(xy), bool), x_mm=xy[:, 0], y_mm=xy[:, 1])


def test_presses_split_into_pieces_are_read_as_one_contact() -> None:
    """Each press also lights a piece a pitch and more away, stronger on every other press (as on the real
    sensor): read as several contacts those presses are placed on the piece; read as one, about right."""
    rng = np.random.default_rng(1)
    true = rng.uniform(-12.0, 12.0, (14, 2))
    truth = _truth(true)
    xy = np.stack([truth.x_mm, truth.y_mm], axis=1)
    one = xy + rng.normal(0.0, 0.5 * PITCH, xy.shape)
    piece = np.where((np.arange(len(xy)) // 2 % 2 == 0)[:, None], rng.normal(0.0, 1.5 * PITCH, xy.shape), 0.0)
    several = one + piece
    got = one_contact_evidence(_read(several), _read(one), truth)
    assert got.adopt and got.several_rms_mm > 1.5 * got.one_rms_mm


@pytest.mark.parametrize("presses", (14, 2))
def test_without_evidence_the_configured_count_stays(presses) -> None:
    """The same placing either way (noise only), or too few presses to tell: several contacts stay."""
    rng = np.random.default_rng(2)
    truth = _truth(rng.uniform(-12.0, 12.0, (presses, 2)))
    xy = np.stack([truth.x_mm, truth.y_mm], axis=1)
    several, one = xy + rng.normal(0.0, 1.0, xy.shape), xy + rng.normal(0.0, 1.0, xy.shape)
    assert not one_contact_evidence(_read(several), _read(one), truth).adopt
    if presses == 2:  # one far better, but two presses are no evidence
        assert not one_contact_evidence(_read(several + 2 * PITCH), _read(xy), truth).adopt


def test_calibrate_centroid_keeps_several_contacts_on_a_sensor_whose_presses_do_not_split(tmp_path) -> None:
    rec = Recording(write_scenario(tmp_path / "unseen", "unseen", seed=4, frames=400))
    bundle, summary = calibrate_centroid(rec, calibrate_fibers(rec.rest_frames(), rec.pixel_format))
    assert bundle.options.max_contacts == summary["max_contacts"] == 4
    assert summary["rms_mm_one"] == pytest.approx(summary["rms_mm_several"], rel=0.05)
    kept, kept_summary = calibrate_centroid(rec, calibrate_fibers(rec.rest_frames(), rec.pixel_format),
                                            contacts="keep")
    assert "max_contacts" not in kept_summary and kept.options.max_contacts == 4


def test_orientation_is_settled_on_the_reading_that_places_the_presses(tmp_path, monkeypatch) -> None:
    """Presses that several contacts a frame misplace (every other one onto a piece two pitches off, as a real
    skin's split presses were) fail the orientation gate read that way; read as one contact a frame they
    settle it, and the bundle records how."""
    from optitac_edge.calibration import steps
    from optitac_edge.calibration.orientation import is_verified

    rec = Recording(write_scenario(tmp_path / "unseen", "unseen", seed=4, frames=400))
    bundle = calibrate_fibers(rec.rest_frames(), rec.pixel_format)
    measure = steps.measure_sessions

    def pieces(recs, b, corrected=True, **kw):
        m, truth = measure(recs, b, corrected, **kw)
        if b.options.max_contacts > 1:
            shift = np.where(np.arange(m.x_mm.size) % 2 == 0, 2.0 * b.layout.pitch_mm, 0.0)
            m = replace(m, x_mm=m.x_mm + shift, y_mm=m.y_mm - shift)
        return m, truth

    monkeypatch.setattr(steps, "measure_sessions", pieces)
    several = steps.press_orientation(*pieces([rec], bundle, corrected=False), bundle)
    assert several.symmetry is None  # the configured reading alone refuses
    fixed, fit = steps.calibrate_orientation(rec, bundle)
    assert fit.symmetry is not None and fit.symmetry.is_identity and is_verified(fixed)
    assert "read as one contact a frame" in fixed.extra_meta["orientation"]["evidence"]
