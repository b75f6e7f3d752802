"""A verdict claims nothing it did not measure (issue 52 §4): every check states its n; zero samples is
"not measured", never ok.

Before: ``evaluate`` printed ``[ok] detection: 74/74 contact frames, 0 false contacts on 0 rest frames``, and
on data without a contact-free frame detection passed the verdict.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from optitac_edge.calibration.measure import measure_recording
from optitac_edge.calibration.verdict import Check, Verdict, judge
from optitac_edge.cli import main
from optitac_edge.io.bundle_file import load_bundle
from optitac_edge.io.recording import Recording


def _rows(truth, keep: np.ndarray):
    """``truth`` with only the rows ``keep`` selects."""
    return dataclasses.replace(truth, **{f.name: getattr(truth, f.name)[keep] for f in dataclasses.fields(truth)
                                         if isinstance(getattr(truth, f.name), np.ndarray)})


def test_presses_without_a_contact_free_frame_do_not_pass_false_contacts(unseen_rec, bundle_path):
    rec, bundle = Recording(unseen_rec), load_bundle(bundle_path)
    m = measure_recording(rec, bundle)
    presses = _rows(rec.truth, rec.truth.contact)
    verdict = judge(bundle, m, presses)
    checks = {c.name: c for c in verdict.checks}
    assert checks["false contacts"].n == 0 and not checks["false contacts"].ok
    assert "[not measured] false contacts: 0 rest frames" in "\n".join(verdict.lines())
    assert "false contacts not measured" in verdict.lines()[0] and not verdict.good
    assert checks["detection"].n == int(rec.truth.contact.sum()) and checks["detection"].ok


def test_a_recording_without_presses_measures_neither_detection_nor_the_centroid(rest_rec, bundle_path, capsys):
    main(["evaluate", str(rest_rec), "--cal", str(bundle_path)])
    out = capsys.readouterr().out
    assert "[not measured] detection: 0 contact frames" in out
    assert "[not measured] centroid: 0 detected contact frames" in out
    assert "[ok] detection" not in out and "[ok] centroid" not in out


@given(n=st.integers(0, 10**6), ok=st.booleans())
def test_a_check_is_ok_only_on_samples(n, ok):
    check = Check("x", ok, "seen", "fix", n=n)
    assert check.ok == (ok and n > 0)
    assert check.line().startswith("  [ok]" if check.ok else "  [FAIL]" if n else "  [not measured]")
    assert Verdict((check,)).good == check.ok
