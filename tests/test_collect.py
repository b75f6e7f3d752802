"""``optitac-edge collect`` over the simulator's virtual rig (sim://): every experiment, limits, rig frame."""

from __future__ import annotations

import numpy as np
import pytest

from optitac_edge.bringup.collect import Collector, CollectSettings
from optitac_edge.bringup.experiments import EXPERIMENTS, plan, spread
from optitac_edge.bringup.rig_frame import fit_rig_frame
from optitac_edge.bringup.rig_recorder import RigRecorder
from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.calibration.orientation import layout_symmetries
from optitac_edge.cli import main
from optitac_edge.core.layout import hex_layout
from optitac_edge.errors import RigError
from optitac_edge.io.recording import Recording
from optitac_edge.sim.rig import parse_sim_url

FAST = CollectSettings(initial_rest_frames=6, rest_frames=3, hold_frames=4, approach_feed_mm_s=30.0, hover_mm=1.0,
                       touch_extra_mm=0.3, shake_s=0.1)


_BUNDLES: dict[str, object] = {}


def _collect(experiment: str, out, url: str, limit: int = 3, settings: CollectSettings = FAST):
    from optitac_edge.bringup.rigs import open_rig
    from optitac_edge.config import load_board_config

    rig, camera = open_rig(load_board_config("sim", env={}), url)
    with rig, camera:
        rest = [camera.read().frame.copy() for _ in range(6)]
        if "sim" not in _BUNDLES:  # the virtual rig's camera is always the same simulated sensor
            _BUNDLES["sim"] = calibrate_fibers(rest, "gray")
        return Collector(camera, rig, _BUNDLES["sim"], settings, prompt=lambda line: None).run(
            experiment, out, limit=limit)


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_collects_over_the_virtual_rig(experiment, tmp_path) -> None:
    out = tmp_path / experiment
    result = _collect(experiment, out, "sim://?rotation=-12&origin=95,84")
    assert result.presses == 3 and result.bundle_symmetry == "as it is"
    rec = Recording(out)
    truth, poses = rec.truth, rec.rig_poses
    assert truth is not None and poses is not None and rec.timestamped
    slides, shakes = experiment == "slide", experiment == "vibrate"
    assert len(poses.frame) == len(rec) and set(poses.phase) == {"rest", "approach", "hold", "release", "move"} | (
        {"slide"} if slides else set()) | ({"shake"} if shakes else set())
    held = np.flatnonzero(poses.phase == "hold")
    presses = spread(plan(experiment, hex_layout()), 3)
    hold = FAST.hold_frames
    # the three presses' hold frames (a slide's: at its start, then at its end; a shaken one's: before and after
    # the shake): the planned position and depth
    places = [[(p.x_mm, p.y_mm)] + ([(p.slide_x_mm, p.slide_y_mm)] if slides else [(p.x_mm, p.y_mm)] if shakes
                                   else []) for p in presses]
    want = np.repeat([xy for each in places for xy in each], hold, axis=0)
    last = truth.contact & (np.isin(truth.frame, held))
    xy = np.stack([truth.x_mm[last], truth.y_mm[last]], 1)[-len(want):]
    assert np.abs(xy - want).max() < 0.3
    depths = np.repeat([p.depth_mm for p in presses for _ in places[0]], hold)
    assert np.abs(truth.depth_mm[last][-len(want):] - depths).max() < 0.1
    assert (truth.motion is not None) == (slides or shakes)
    frame = rec.meta.extra["collect"]["rig_frame"]
    assert abs(frame["rotation_deg"] + 12.0) < 0.5


def test_collect_from_the_command_line(tmp_path, capsys) -> None:
    out = tmp_path / "seen"
    assert main(["collect", "seen", "--rig", "sim://", "-o", str(out), "--limit", "2"]) == 0
    stdout = capsys.readouterr().out
    assert "touch-off" in stdout and f"wrote {out}: seen, 2 presses" in stdout
    assert Recording(out).meta.extra["collect"]["presses"] == 2
    # minutes without a word before (issue 38, item 28): a line a press where the output is not a terminal
    # issue 52 §5: the first line said 'about 0 min left' (no press timed yet); the last has nothing left
    assert "press 1 of 2 done\n" in stdout and "press 2 of 2 done\n" in stdout and "0 min left" not in stdout


def test_the_time_left_is_said_from_timed_presses_only() -> None:
    from optitac_edge.cli.commands.collect import _left

    assert _left(0.0, 0, 10) == "" and _left(120.0, 1, 0) == ""
    assert _left(30.0, 1, 1) == "; under a minute left"
    assert _left(120.0, 2, 10) == "; about 10 min left"


def test_the_rig_frame_and_surface_are_found_not_typed_in(tmp_path, capsys) -> None:
    out = tmp_path / "r"
    _collect("repeat", out, "sim://?rotation=23&origin=110,70&surface=-1.5", limit=1,
             settings=CollectSettings(initial_rest_frames=10, rest_frames=5, hold_frames=4))
    frame = Recording(out).meta.extra["collect"]["rig_frame"]
    assert abs(frame["rotation_deg"] - 23.0) < 0.3
    assert np.hypot(frame["origin_xy_mm"][0] - 110.0, frame["origin_xy_mm"][1] - 70.0) < 0.2
    assert abs(frame["surface_z_mm"] + 1.5) < 0.05


def test_a_mirrored_mount_is_reported_as_a_bundle_to_reorient(tmp_path) -> None:
    result = _collect("unseen", tmp_path / "r", "sim://?mirror=1", limit=1)
    assert "mirrored" in result.bundle_symmetry


def test_a_target_outside_the_limits_is_refused_before_the_rig_moves(tmp_path, capsys) -> None:
    board = tmp_path / "board.toml"
    board.write_text("[rig]\nx_min = 40.0\nx_max = 160.0\ny_min = 20.0\ny_max = 140.0\nz_min = -0.5\nz_max = 20.0\n")
    # the skin's surface is at z = 2: registration (2 mm deep) fits, a 3 mm deep press needs z = -1, below z_min
    assert main(["collect", "seen", "--board", str(board), "--rig", "sim://", "-o", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "outside the limits" in err[0]
    assert "nothing moved" in err[0]


def test_a_real_rig_without_limits_is_refused(tmp_path, capsys) -> None:
    assert main(["collect", "seen", "--rig", "gcode:///dev/optitac-no-such-port", "-o", str(tmp_path / "r")]) == 2
    assert "set the rig's travel limits" in capsys.readouterr().err


@pytest.mark.parametrize("url, message", [
    ("sim://?spin=3", "unknown key 'spin'"), ("sim://?rotation=abc", "finite numbers"),
    ("ftp://x", "unknown rig URL"), ("sim://host/path", "sim://?key=value"),
    ("gcode:/dev/ttyUSB0", "unknown rig URL"), ("ur:host", "unknown rig URL"),
    ("sim://?physics=rubber", "unknown physics 'rubber'"),
])
def test_bad_rig_urls_are_one_line(url, message, tmp_path, capsys) -> None:
    assert main(["collect", "seen", "--rig", url, "-o", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err


def test_continuing_with_other_arguments_is_refused(tmp_path, capsys) -> None:
    from optitac_edge.bringup.collect import JOURNAL

    out = tmp_path / "r"
    out.mkdir()
    (out / "incomplete.json").write_text('{"reason": "interrupted", "frames_written": 0, "frames": 256}')
    (out / JOURNAL).write_text('{"kind": "setup", "experiment": "unseen", "seed": 0, "presses": 10}\n')
    assert main(["collect", "seen", "--rig", "sim://", "-o", str(out), "--limit", "2"]) == 2
    assert "an interrupted collection of unseen" in capsys.readouterr().err


def test_rig_frame_fit_recovers_rotation_origin_and_the_bundles_symmetry() -> None:
    sym = layout_symmetries(hex_layout())
    rng = np.random.default_rng(0)
    rig = np.array([[100, 80], [106, 80], [100, 86], [94, 80], [100, 74]], dtype=float)
    theta = np.radians(-17.0)  # sensor +x at -17 degrees from the rig's +X
    d = rig - (101.0, 79.0)
    c, s = np.cos(-theta), np.sin(-theta)
    sensor = np.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]], 1)
    for h in (sym[0], sym[2], sym[9]):
        frame, found = fit_rig_frame(rig, h.apply(sensor) + rng.normal(0, 0.05, sensor.shape), 2.0, sym, 1.5)
        assert found.label == h.label
        assert abs(frame.rotation_deg + 17.0) < 1.0 and np.allclose(frame.origin_xy_mm, (101.0, 79.0), atol=0.1)
        assert np.allclose(frame.to_sensor(rig), sensor, atol=0.15)
        assert np.allclose(frame.to_rig(frame.to_sensor(rig)), rig)


def test_a_centroid_that_reads_the_presses_closer_together_is_a_scale_not_a_bad_registration() -> None:
    """An uncalibrated centroid reads presses towards the array's middle (0.80 of their spacing on a 61-fiber
    array): the rigid fit's residual is that scale's, not the rig's; the frame keeps the rigid rotation and
    origin, and is judged by the residual once the scale is allowed."""
    sym = layout_symmetries(hex_layout(rings=4, pitch_mm=4.0))
    rig = np.array([[100, 80], [107.2, 80], [100, 87.2], [92.8, 80], [100, 72.8]], dtype=float)
    sensor = 0.8 * (rig - (100.5, 79.5))
    frame, found = fit_rig_frame(rig, sensor, 2.0, sym, 4.0)
    assert found.is_identity and abs(frame.rotation_deg) < 1e-9
    assert frame.fit_rms_mm == pytest.approx(0.2 * 7.2 * np.sqrt(4 / 5))  # the four outer presses 1.44 mm off
    assert frame.centroid_scale == pytest.approx(0.8) and frame.shape_rms_mm < 1e-9
    assert np.allclose(frame.origin_xy_mm, (100.5, 79.5), atol=0.2)  # the scale moves it by 0.2 of the offset


def test_sim_url_parsing() -> None:
    mount = parse_sim_url("sim://?rotation=5&origin=1,2&surface=-3&mirror=1")
    assert mount.rotation_deg == 5 and mount.origin_xy_mm == (1.0, 2.0) and mount.surface_z_mm == -3 and mount.mirror
    with pytest.raises(RigError):
        parse_sim_url("sim://?origin=1")


def test_ctrl_c_retracts_and_exits_130_saying_how_to_continue(tmp_path) -> None:
    import signal
    import subprocess
    import sys

    out = tmp_path / "r"
    # as from a terminal: Ctrl-C raises KeyboardInterrupt even when the tests themselves run in the
    # background (a shell starts background jobs with SIGINT ignored, and Python keeps it so)
    start = ("import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
             "sys.argv = ['optitac-edge', *sys.argv[1:]]; runpy.run_module('optitac_edge.cli', run_name='__main__')")
    proc = subprocess.Popen([sys.executable, "-c", start, "collect", "seen", "--rig", "sim://", "-o", str(out),
                             "--limit", "40"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.startswith("sensor origin at rig"):  # registration done: the experiment's presses begin
            break
    proc.send_signal(signal.SIGINT)
    rest, err = proc.communicate(timeout=60)
    assert proc.returncode == 130
    assert "retracted the tip to z = 12 mm" in rest
    assert err.strip().splitlines()[-1] == (
        f"optitac-edge: interrupted: tip retracted; recording {out} is incomplete: run the same command again to "
        "continue after the last complete press")
    from optitac_edge.errors import RecordingError

    with pytest.raises(RecordingError, match="interrupted collection"):
        Recording(out)


def test_limit_spreads_the_presses_over_the_whole_experiment() -> None:
    """--limit 40 took the first 40: shapes held only edges, unseen only the x axis."""
    layout = hex_layout()
    shapes = spread(plan("shapes", layout), 40)
    assert len(shapes) == 40 and {p.shape for p in shapes} == {"edge", "circle", "square", "ellipse", "triangle"}
    unseen = spread(plan("unseen", layout), 40)
    assert any(p.y_mm != 0 for p in unseen) and any(p.x_mm != 0 for p in unseen)
    full = plan("seen", layout)
    assert spread(full, None) == full and spread(full, 10**6) == full
    picked = spread(full, 7)
    assert len(picked) == 7 and picked[0] == full[0] and picked[-1] == full[-1]
    assert [full.index(p) for p in picked] == sorted(full.index(p) for p in picked)


def test_the_estimates_of_several_frames_are_each_frames_own(tmp_path, monkeypatch) -> None:
    """Bug: the touch-off (2 of 3 frames in contact) and the registration (the mean of the hold frames)
    read a list holding the pipeline's one reused estimate n times: the last frame's, n times."""
    seen: list[list[int]] = []
    frames = RigRecorder.frames

    def spy(self, n, phase, press):
        got = frames(self, n, phase, press)
        seen.append([id(e) for e in got])  # the list holds them all: equal ids are one object
        return got

    monkeypatch.setattr(RigRecorder, "frames", spy)
    _collect(EXPERIMENTS[0], tmp_path / "c", "sim://", limit=1)
    assert seen and all(len(set(f)) == len(f) for f in seen), seen


def test_a_slide_collection_is_evaluated_for_its_motion(tmp_path, capsys) -> None:
    """``collect slide`` on the virtual rig at 240 fps, then ``evaluate``: truth.csv's motion comes from the rig's
    pose; the velocity, the onsets and the held frames are scored (the rig's feed limit, 20 mm/s, caps the two
    fastest slides)."""
    from optitac_edge.bringup.rigs import open_rig
    from optitac_edge.calibration.measure import measure_recording
    from optitac_edge.calibration.motion_report import motion_report
    from optitac_edge.config import load_board_config

    rig, camera = open_rig(load_board_config("sim", env={}, overrides={"camera.fps": 240}), "sim://?rotation=20")
    with rig, camera:
        bundle = calibrate_fibers([camera.read().frame.copy() for _ in range(6)], "gray")
        settings = CollectSettings(initial_rest_frames=12, rest_frames=6, hold_frames=30, approach_feed_mm_s=30.0,
                                   hover_mm=1.0, touch_extra_mm=0.3)
        Collector(camera, rig, bundle, settings, prompt=lambda line: None).run("slide", tmp_path / "slide")
    rec = Recording(tmp_path / "slide")
    truth = rec.truth
    assert truth.motion is not None and "sliding" in set(truth.motion)
    speeds = np.hypot(truth.vx_mm_s, truth.vy_mm_s)[truth.motion == "sliding"]
    assert np.median(speeds) > 1.5 and speeds.max() < 20.5  # 2 mm/s ... the feed limit
    report = motion_report(measure_recording(rec, bundle, progress=False), truth, rec.meta.fps)
    assert report is not None and report.velocity_rmse_mm_s <= 3.0
    fast = [f for s, f in report.onsets if s >= 10.0]
    assert len(fast) >= 3 and all(f is not None and f <= 3 for f in fast), report.onsets
    assert report.false_slips == 0 and max(report.ids_per_press) == 1


def test_a_vibrate_collection_shakes_each_press_and_its_events_are_scored(tmp_path) -> None:
    """``collect vibrate`` on the virtual rig at 240 fps, three of its presses (30 Hz along the rig's x, 60 Hz along y,
    100 Hz along z) shaken by 0.05 mm: ``evaluate`` finds every shake within 5 frames and no event in the quiet
    holds."""
    from optitac_edge.bringup.rigs import open_rig
    from optitac_edge.calibration.measure import measure_recording
    from optitac_edge.calibration.motion_report import motion_report
    from optitac_edge.config import load_board_config

    rig, camera = open_rig(load_board_config("sim", env={}, overrides={"camera.fps": 240}), "sim://?rotation=20")
    with rig, camera:
        bundle = calibrate_fibers([camera.read().frame.copy() for _ in range(6)], "gray")
        settings = CollectSettings(initial_rest_frames=12, rest_frames=6, hold_frames=70, approach_feed_mm_s=30.0,
                                   hover_mm=1.0, touch_extra_mm=0.3, shake_s=0.1)
        Collector(camera, rig, bundle, settings, prompt=lambda line: None).run("vibrate", tmp_path / "vib", limit=3)
    rec = Recording(tmp_path / "vib")
    assert set(rec.rig_poses.phase) >= {"shake"} and "vibrating" in set(rec.truth.motion)
    report = motion_report(measure_recording(rec, bundle, progress=False), rec.truth, rec.meta.fps)
    assert report is not None and len(report.shakes) == 3
    assert all(f is not None and f <= 5 for f in report.shakes), report.shakes
    assert report.false_vibrations == 0 and report.false_slips == 0


def test_a_rig_that_cannot_shake_refuses_vibrate_before_moving(tmp_path) -> None:
    from optitac_edge.bringup.rigs import open_rig
    from optitac_edge.config import load_board_config

    rig, camera = open_rig(load_board_config("sim", env={}), "sim://")
    type(rig).shakes = False
    try:
        with rig, camera, pytest.raises(RigError, match="cannot shake the tip"):
            bundle = calibrate_fibers([camera.read().frame.copy() for _ in range(6)], "gray")
            Collector(camera, rig, bundle, FAST, prompt=lambda line: None).run("vibrate", tmp_path / "v", limit=2)
        assert rig.moves == 0 and not (tmp_path / "v").exists()
    finally:
        type(rig).shakes = True


def test_a_61_fiber_array_is_collected_on_the_simulated_rig_from_its_layout(tmp_path, capsys) -> None:
    """The bring-up's collection on another array: the board names the layout for the simulated camera and for
    calibration; the rig's first collection maps 61 fibers, presses the 13.35 mm circle (the 5 mm one at 4 mm
    pitch) and registers within the pitch-scaled gate; levels and orientation calibrate from it."""
    from optitac_edge.io.bundle_file import load_bundle

    layout = tmp_path / "hex61.csv"
    assert main(["layout", "--rings", "4", "--pitch-mm", "4", "-o", str(layout)]) == 0
    board = tmp_path / "b61.toml"
    board.write_text(f"""config_version = 1
[sensor]
id = 0
[camera]
backend = "sim"
fps = 60
warmup_frames = 0
[camera.options]
layout = "{layout}"
[calibration]
bundle = "{tmp_path / 'cal.npz'}"
layout = "{layout}"
rest_frames = 10
[link]
transport = "none"
""")
    out = tmp_path / "seen"
    assert main(["collect", "seen", "--rig", "sim://", "--board", str(board), "-o", str(out), "--limit", "14"]) == 0
    text = capsys.readouterr().out
    assert "warning: registration" not in text  # it was 1.29 mm on every such collection: the centroid's scale
    assert "with the uncalibrated centroid's scale 0.80" in text
    rec = Recording(out)
    assert rec.truth is not None and set(rec.truth.size_mm[rec.truth.contact]) == {13.35}
    assert rec.layout is not None and rec.layout.n_fibers == 61  # kept for calibrate fibers (it was not)
    cal = tmp_path / "cal.npz"
    assert load_bundle(cal).layout.n_fibers == 61
    assert main(["calibrate", "levels", str(out), "--cal", str(cal)]) == 0
    assert main(["calibrate", "orientation", str(out), "--cal", str(cal)]) == 0
    assert "confirmed" in capsys.readouterr().out


def test_a_collection_interrupted_while_parking_continues_into_a_readable_recording(tmp_path, monkeypatch) -> None:
    """Ctrl-C during the park after the last press, then the same command: the continued collection took a
    fresh baseline (frames) and wrote no truth rows for it, then called itself complete; every reader said
    'truth.csv: rows for 1166 of the recording's 1176 frames' and only --fresh got out."""
    from optitac_edge.bringup import collect as collect_module

    out = tmp_path / "seen"
    real_park = collect_module.Collector._park

    def interrupted_park(self) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(collect_module.Collector, "_park", interrupted_park)
    with pytest.raises(KeyboardInterrupt):
        _collect("seen", out, "sim://", limit=2)
    monkeypatch.setattr(collect_module.Collector, "_park", real_park)
    result = _collect("seen", out, "sim://", limit=2)
    rec = Recording(out)  # readable: truth.csv has a row for every frame (the reader checks)
    assert result.resumed_at == 2 and rec.truth is not None and len(rec) == result.frames


def test_ctrl_c_while_starting_says_nothing_moved(tmp_path, monkeypatch, capsys) -> None:
    """Ctrl-C during collect's start-up (the camera or the bundle still opening) said 'tip retracted; recording
    early is incomplete' when nothing had moved and nothing existed (issue 38, item 22)."""
    from optitac_edge.service import bundles

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(bundles, "obtain_bundle", interrupted)
    out = tmp_path / "early"
    assert main(["collect", "seen", "--rig", "sim://", "-o", str(out), "--limit", "2"]) == 130
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err == (f"optitac-edge: interrupted: nothing moved and nothing was recorded (interrupted while starting; "
                   f"{out} unchanged)")
    assert not out.exists()
