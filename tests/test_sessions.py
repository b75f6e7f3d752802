"""Sessions (issue 37): a recording's tare points, and several recordings (days) calibrated and evaluated
together, each with its own baseline."""

from __future__ import annotations

import json

import numpy as np
import pytest

from optitac_edge.calibration.evaluation import detection, press_ids
from optitac_edge.calibration.measure import measure_recording, measure_sessions
from optitac_edge.calibration.steps import calibrate_centroid
from optitac_edge.cli import main
from optitac_edge.io.bundle_file import load_bundle
from optitac_edge.io.recording import Recording, RecordingMeta
from optitac_edge.io.recording_writer import RecordingWriter
from optitac_edge.sim.scenarios import write_scenario
from optitac_edge.sim.sensor import SimulatedSensor
from optitac_edge.sim.skin import Indenter


def _write(path, plan, gains, tares=None) -> Recording:
    """A recording of ``plan`` (None: rest, else an indenter), frame ``k``'s fibers at ``gains[k]`` times
    their light (a day's per-fiber change), ``tares`` in its meta."""
    sensor = SimulatedSensor(seed=5)
    extra = {} if tares is None else {"tares": tares}
    meta = RecordingMeta(rest_frames=10, fps=60.0, extra=extra)
    with RecordingWriter(path, len(plan), sensor.frame_shape, meta, with_truth=True) as w:
        for k, press in enumerate(plan):
            dark = sensor.darkening(() if press is None else (press,))
            w.write(k, sensor.frame_from_darkening(1.0 - (1.0 - dark) * gains[k]), round(k * 1e9 / 60))
            w.write_truth(k, press)
    return Recording(path)


@pytest.fixture(scope="module")
def two_days(tmp_path_factory, bundle_path):
    """Rest, presses, then some fibers 30 % darker and others 30 % brighter (another day's skin) with rest
    frames where a tare retakes the baseline, then presses again."""
    rng = np.random.default_rng(1)
    n = SimulatedSensor().layout.n_fibers
    day2 = np.ones(n)
    changed = rng.choice(n, 40, replace=False)
    day2[changed[:20]], day2[changed[20:]] = 0.7, 1.3
    press = [Indenter("circle", float(x), float(y), 0.0, 5.0, 3.0) for x, y in rng.uniform(-7, 7, (12, 2))]
    plan: list[Indenter | None] = [None] * 10
    for p in press[:6]:
        plan += [p, p, None]
    first = len(plan)
    plan += [None] * 12
    for p in press[6:]:
        plan += [p, p, None]
    gains = [np.ones(n) if k < first else day2 for k in range(len(plan))]
    root = tmp_path_factory.mktemp("sessions")
    return (_write(root / "tared", plan, gains, tares=[first]), _write(root / "untared", plan, gains),
            first, load_bundle(bundle_path))


def test_a_tare_point_retakes_the_baseline_in_replay_and_evaluation(two_days) -> None:
    """Without the tare the fibers 30 % darker are a contact in every later frame; with it listed in
    meta.json, replay and evaluate take the baseline again there: no false contact, every press found."""
    tared, untared, first, bundle = two_days
    assert [t.frame for t in tared.tares] == [first] and untared.tares == ()
    m = measure_recording(tared, bundle)
    d = detection(m, tared.truth)
    assert d.false_contacts == 0 and d.detected == d.contact_frames == 24
    bad = detection(measure_recording(untared, bundle), untared.truth)
    assert bad.false_contacts > 10


def test_the_replay_command_honours_the_tare(two_days, tmp_path, capsys) -> None:
    """The command line gives what the function gives: 24 frames with contact (the presses), none else."""
    from optitac_edge.io.bundle_file import save_bundle

    tared, _, _, bundle = two_days
    cal = tmp_path / "cal.npz"
    save_bundle(bundle, cal)
    assert main(["replay", str(tared.path), "--cal", str(cal), "-o", str(tmp_path / "c.csv")]) == 0
    assert "24 with contact" in capsys.readouterr().out


@pytest.mark.parametrize("tares, why", [
    ("5", "must be a list"), ([0], "tares\\[0\\]"), ([12, 12], "tares\\[1\\]"), ([{"frame": 20, "frames": 0}], "K >= 1"),
    ([{"frame": 20, "extra": 1}], "tares\\[0\\]"), ([10_000], "tares\\[0\\]"), ([True], "tares\\[0\\]"),
])
def test_bad_tares_are_one_line(tmp_path, rest_rec, tares, why, capsys) -> None:
    import shutil

    rec = tmp_path / "rec"
    shutil.copytree(rest_rec, rec)
    meta = json.loads((rec / "meta.json").read_text())
    meta["tares"] = tares
    (rec / "meta.json").write_text(json.dumps(meta))
    assert main(["replay", str(rec), "--cal", str(rec), "-o", str(tmp_path / "c.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "meta.json" in err
    import re

    assert re.search(why, err), err


@pytest.fixture(scope="module")
def seen_days(tmp_path_factory):
    root = tmp_path_factory.mktemp("days")
    return [Recording(write_scenario(root / f"seen{day}", "seen", seed=10 + day, day=day, frames=160))
            for day in (1, 2)]


def test_several_recordings_calibrate_and_evaluate_as_one(seen_days, bundle_path, tmp_path, capsys) -> None:
    """Two days' presses: measured each with its own baseline and joined, no press spans the two (the last
    press of one and the first of the next are the same pose), the centroid map fitted to both; the command
    line takes both, and evaluate scores both."""
    bundle = load_bundle(bundle_path)
    m, truth = measure_sessions(seen_days, bundle, corrected=False)
    n0 = len(seen_days[0])
    assert len(m) == n0 + len(seen_days[1]) and truth.session is not None
    assert set(truth.frame[truth.session == 1]) <= set(range(n0, len(m)))
    ids = press_ids(truth)
    one = [press_ids(r.truth).max() + 1 for r in seen_days]
    assert ids.max() + 1 == sum(one)  # the same poses on both days are two presses each, never merged
    _, summary = calibrate_centroid(seen_days, bundle)
    assert summary["presses"] == sum(one)
    cal = tmp_path / "cal.npz"
    import shutil

    shutil.copy(bundle_path, cal)
    paths = [str(r.path) for r in seen_days]
    assert main(["calibrate", "centroid", *paths, "--cal", str(cal)]) == 0
    assert f"presses {sum(one)}" in capsys.readouterr().out
    assert main(["evaluate", *paths, "--cal", str(cal)]) == 0
    out = capsys.readouterr().out
    frames = sum(int(r.truth.contact.sum()) for r in seen_days)
    assert f"/{frames} contact frames" in out and ", ".join(paths) in out
