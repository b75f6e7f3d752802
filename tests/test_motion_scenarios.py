"""The simulator's moving presses (``slide``, ``vibrate``, ``hold``), their truth columns and ``evaluate``'s
motion metrics on them."""

from __future__ import annotations

import itertools
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from optitac_edge.errors import RecordingError
from optitac_edge.io.recording import MOTION_COLUMNS, Recording, read_truth
from optitac_edge.sim.motion_scenarios import (
    MOTION_FPS,
    MOTION_REST_FRAMES,
    SLIDE_SPEEDS_MM_S,
    VIBRATE_AMPLITUDE_MM,
    VIBRATE_HZ,
    motion_schedule,
)


def test_a_slides_truth_velocity_is_its_path() -> None:
    plan = motion_schedule("slide")
    assert all(f.indenter is None for f in plan[:MOTION_REST_FRAMES])
    speeds = []
    for a, b in itertools.pairwise(plan):
        if b.motion == "sliding":
            v = ((b.indenter.x_mm - a.indenter.x_mm) * MOTION_FPS, (b.indenter.y_mm - a.indenter.y_mm) * MOTION_FPS)
            assert v == pytest.approx((b.vx_mm_s, b.vy_mm_s), abs=1e-6)
            speeds.append(round(math.hypot(*v), 6))
        elif b.motion in ("held", "pressing") and a.indenter is not None and b.indenter is not None:
            assert (a.indenter.x_mm, a.indenter.y_mm) == pytest.approx((b.indenter.x_mm, b.indenter.y_mm), abs=1e-9)
    assert set(speeds) == set(SLIDE_SPEEDS_MM_S)
    press = [f for f in plan if f.press == len(SLIDE_SPEEDS_MM_S) and f.motion == "sliding"]
    travel = sum(math.hypot(f.vx_mm_s, f.vy_mm_s) / MOTION_FPS for f in press)
    assert travel == pytest.approx(30.0)  # the last press slides 30 mm


def test_a_shake_is_its_amplitude_at_its_frequency() -> None:
    plan = motion_schedule("vibrate")
    runs = 0
    k = 0
    while k < len(plan):
        if plan[k].motion != "vibrating":
            k += 1
            continue
        run = [plan[j] for j in range(k, len(plan)) if plan[j].motion == "vibrating" and plan[j].press == plan[k].press]
        d = np.array([(f.indenter.x_mm - 1.0, f.indenter.y_mm + 0.5, f.indenter.depth_mm - 2.5) for f in run])
        assert 0.85 * VIBRATE_AMPLITUDE_MM <= np.abs(d).max() <= VIBRATE_AMPLITUDE_MM + 1e-9  # sampled at 240 fps
        spectrum = np.abs(np.fft.rfft(d[:, np.argmax(np.abs(d).max(axis=0))]))
        hz = np.fft.rfftfreq(len(run), 1 / MOTION_FPS)[np.argmax(spectrum)]
        assert hz == pytest.approx(VIBRATE_HZ[runs // 3], abs=MOTION_FPS / len(run))
        runs += 1
        k += len(run)
    assert runs == 3 * len(VIBRATE_HZ)


def test_a_hold_never_moves_and_its_length_is_asked_for() -> None:
    plan = motion_schedule("hold", seed=3, frames=20_000)
    assert len(plan) == 20_000 and {f.motion for f in plan} == {"", "pressing", "held"}
    pressed = [f for f in plan if f.indenter is not None]
    assert all(f.vx_mm_s == 0.0 == f.vy_mm_s for f in pressed)
    depths = [f.indenter.depth_mm for f in pressed if f.motion == "held"]
    assert max(depths) - min(depths) > 0.9  # it breathes


def test_motion_truth_is_written_and_read_back(tmp_path) -> None:
    path = tmp_path / "truth.csv"
    head = "frame,contact,shape,x_mm,y_mm,angle_deg,size_mm,depth_mm," + ",".join(MOTION_COLUMNS)
    path.write_text(head + "\n0,0,,,,,,,,,\n1,1,circle,0.5,0.5,0,5,2.5,10.0000,-2.5000,sliding\n")
    truth = read_truth(path, 2)
    assert truth.motion is not None and list(truth.motion) == ["", "sliding"]
    assert truth.vx_mm_s[1] == 10.0 and truth.vy_mm_s[1] == -2.5 and math.isnan(truth.vx_mm_s[0])


@pytest.mark.parametrize(("row", "why"), [
    ("1,1,circle,0.5,0.5,0,5,2.5,1,1,skidding", "motion must be one of"),
    ("1,0,,,,,,,1,1,held", "motion must be one of"),
    ("1,1,circle,0.5,0.5,0,5,2.5,1e9,1,held", "velocity at most"),
    ("1,1,circle,0.5,0.5,0,5,2.5,fast,1,held", "not a number"),
])
def test_bad_motion_truth_is_refused_in_one_line(tmp_path, row: str, why: str) -> None:
    path = tmp_path / "truth.csv"
    path.write_text("frame,contact,shape,x_mm,y_mm,angle_deg,size_mm,depth_mm," + ",".join(MOTION_COLUMNS)
                    + "\n0,0,,,,,,,,,\n" + row + "\n")
    with pytest.raises(RecordingError, match=why):
        read_truth(path, 2)


@pytest.fixture(scope="module")
def slide_rec(tmp_path_factory) -> Path:
    """``sim --scenario slide --day 2`` (the command's own code, in this process)."""
    from optitac_edge.cli import main

    out = tmp_path_factory.mktemp("motion") / "slide"
    assert main(["sim", str(out), "--scenario", "slide", "--day", "2"]) == 0
    # issue 38 item 28: a 240 fps motion scenario keeps each fiber's light by default (raw frames: ~1 GB)
    assert Recording(out).meta.extra["frame_storage"]["storage"] == "fibers"
    assert sum(f.stat().st_size for f in out.rglob("*") if f.is_file()) < 50e6
    return out


def test_evaluate_reports_slides_on_a_simulated_slide(slide_rec, bundle_path) -> None:
    """``sim --scenario slide`` on another day, then ``evaluate``: the targets of the motion work."""
    assert Recording(slide_rec).truth.motion is not None
    run = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "evaluate", str(slide_rec), "--cal",
                          str(bundle_path)], capture_output=True, text=True, check=True)
    lines = {line.split(":")[0]: line for line in run.stdout.splitlines()}
    rmse = float(lines["velocity (steady 5-frame windows)"].split("RMSE ")[1].split(" ")[0])
    assert rmse <= 3.0
    onsets = lines["slides found after (frames of sliding; -"].split("): ")[1].split(", ")
    fast = [o for o in onsets if float(o.split(" mm/s")[0]) >= 10]
    assert fast and all(o.split()[-1] != "-" and int(o.split()[-1]) <= 3 for o in fast)
    assert lines["false slips"].startswith("false slips: 0 in") and "max 1 over 7 presses" in lines["false slips"]


def test_replay_writes_each_frames_motion_to_the_contacts_csv(slide_rec, tmp_path, bundle_path) -> None:
    import csv

    from optitac_edge.cli import main

    out = slide_rec
    assert main(["replay", str(out), "--cal", str(bundle_path), "-o", str(tmp_path / "c.csv")]) == 0
    rows = list(csv.DictReader((tmp_path / "c.csv").open()))
    truth = Recording(out).truth
    sliding = [r for r in rows if r["sliding"] == "1"]
    assert sliding and all(int(r["slide_frame"]) <= int(r["frame"]) for r in sliding)

    def whole_window(k: int) -> bool:  # sliding at one velocity over the velocity window
        return all(truth.motion[k - j] == "sliding" and truth.vx_mm_s[k - j] == truth.vx_mm_s[k]
                   and truth.vy_mm_s[k - j] == truth.vy_mm_s[k] for j in range(5))

    steady = [r for r in sliding if whole_window(int(r["frame"]))]
    assert len(steady) > 100
    for r in steady:  # a whole window sliding: the velocity is the truth's (within 3 mm/s or 5 %)
        k = int(r["frame"])
        tolerance = max(3.0, 0.05 * math.hypot(truth.vx_mm_s[k], truth.vy_mm_s[k]))
        assert float(r["vx_mm_s"]) == pytest.approx(truth.vx_mm_s[k], abs=tolerance)
        assert float(r["vy_mm_s"]) == pytest.approx(truth.vy_mm_s[k], abs=tolerance)
    rest = [r for r in rows if r["contact"] == "0"]
    assert all(r["vx_mm_s"] == "" and r["slide_frame"] == "-1" for r in rest)
    assert all(0.0 <= float(r["vibration"]) < 1e6 for r in rows[MOTION_REST_FRAMES:])
