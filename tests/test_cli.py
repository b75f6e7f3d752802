"""The command line: the documented commands work and bad input ends in one line, exit 2."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from optitac_edge.cli import main
from optitac_edge.io.bundle_file import load_bundle
from optitac_edge.io.recording import Recording, RecordingMeta
from optitac_edge.io.recording_writer import RecordingWriter


def _one_line_error(capsys, argv, *needles):
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.startswith("optitac-edge: error:") and "\n" not in err and "Traceback" not in err
    for needle in needles:
        assert needle in err, err
    return err


def test_sim_calibrate_replay_round_trip(tmp_path, unseen_rec, bundle_path, capsys):
    out = tmp_path / "contacts.csv"
    assert main(["replay", str(unseen_rec), "--cal", str(bundle_path), "-o", str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    rec = Recording(unseen_rec)
    assert len(rows) == len(rec)
    assert set(rows[0]) >= {"frame", "contact", "x_mm", "y_mm", "major_mm", "minor_mm", "angle_deg",
                            "strength", "shape", "confidence"}
    assert not list(tmp_path.glob("*.tmp"))


def test_missing_recording(capsys, tmp_path, bundle_path):
    _one_line_error(capsys, ["replay", str(tmp_path / "nope"), "--cal", str(bundle_path), "-o",
                             str(tmp_path / "c.csv")], "not found")
    assert not (tmp_path / "c.csv").exists()


def test_garbled_recording(capsys, tmp_path, bundle_path, rest_rec):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "meta.json").write_text(json.dumps({"rest_frames": 10, "fps": 60}))
    (bad / "frames.npy").write_bytes(b"\x93NUMPY garbage")
    _one_line_error(capsys, ["replay", str(bad), "--cal", str(bundle_path), "-o", str(tmp_path / "c.csv")],
                    "frames.npy")
    _one_line_error(capsys, ["calibrate", "fibers", str(bad), "-o", str(tmp_path / "x.npz")], "frames.npy")


def test_frames_of_the_wrong_size_for_the_bundle(capsys, tmp_path, bundle_path):
    small = tmp_path / "small"
    assert main(["sim", str(small), "--scenario", "rest", "--frames", "12", "--width", "320",
                 "--height", "240"]) == 0
    _one_line_error(capsys, ["replay", str(small), "--cal", str(bundle_path), "-o", str(tmp_path / "c.csv")],
                    "built for 640x480")
    rgb = tmp_path / "rgb"
    assert main(["sim", str(rgb), "--scenario", "rest", "--frames", "12", "--rgb"]) == 0
    _one_line_error(capsys, ["replay", str(rgb), "--cal", str(bundle_path), "-o", str(tmp_path / "c.csv")],
                    "gray")


@pytest.mark.parametrize("damage", ["truncate", "flip", "empty", "text"])
def test_corrupted_or_truncated_bundle(capsys, tmp_path, bundle_path, rest_rec, damage):
    data = bundle_path.read_bytes()
    bad = tmp_path / "bad.npz"
    if damage == "truncate":
        bad.write_bytes(data[: len(data) // 3])
    elif damage == "flip":
        b = bytearray(data)
        b[len(b) // 2] ^= 0xFF
        bad.write_bytes(bytes(b))
    elif damage == "empty":
        bad.write_bytes(b"")
    else:
        bad.write_text("hello")
    _one_line_error(capsys, ["replay", str(rest_rec), "--cal", str(bad), "-o", str(tmp_path / "c.csv")],
                    str(bad))


@pytest.mark.parametrize("fill", [0, 255])
def test_rest_frames_without_fibers_are_refused(capsys, tmp_path, fill):
    path = tmp_path / f"flat{fill}"
    with RecordingWriter(path, 10, (480, 640), RecordingMeta(rest_frames=10, fps=60.0)) as w:
        for i in range(10):
            w.write(i, np.full((480, 640), fill, np.uint8))
    _one_line_error(capsys, ["calibrate", "fibers", str(path), "-o", str(tmp_path / "cal.npz")], "fiber")
    assert not (tmp_path / "cal.npz").exists()


def test_usage_errors_are_one_line(capsys):
    with pytest.raises(SystemExit) as info:
        main(["sim", "/tmp/x", "--scenario", "nope"])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "invalid choice" in err


def test_installed_console_script_reports_without_traceback(tmp_path):
    """The real process: exit status 2 and one stderr line, no traceback."""
    proc = subprocess.run([sys.executable, "-m", "optitac_edge.cli", "replay", str(tmp_path / "absent"),
                           "--cal", str(tmp_path / "absent.npz"), "-o", str(tmp_path / "c.csv")],
                          check=False, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


def test_run_calibrates_itself_and_stops_cleanly_on_ctrl_c():
    proc = subprocess.Popen([sys.executable, "-m", "optitac_edge.cli", "run", "--fps", "100"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        lines = []
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            lines.append(line)
            if "running" in line or not line:
                break
        assert any("running" in line for line in lines), lines
        time.sleep(0.5)  # the loop is running (no status line: stdout is not a terminal)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=20)
    finally:
        proc.kill()
    assert proc.returncode == 130, err  # interrupted, never a success status
    assert "Traceback" not in err
    assert "processed" in out and "interrupted: the service stopped cleanly" in err


def test_run_with_frame_limit_reports_contacts(tmp_path, capsys):
    assert main(["run", "--fps", "1000", "--frames", "400"]) == 0
    out = capsys.readouterr().out
    assert "processed 400 frames" in out


def test_record_saves_a_live_source_as_a_recording(tmp_path, capsys):
    out = tmp_path / "rec"
    assert main(["record", "--board", "sim", "-o", str(out), "--frames", "30"]) == 0
    rec = Recording(out)
    assert len(rec) == 30 and rec.meta.rest_frames == 10 and rec.pixel_format == "gray"
    assert main(["calibrate", "fibers", str(out), "-o", str(tmp_path / "cal.npz")]) == 0
    assert "217/217 fibers found" in capsys.readouterr().out


def test_bad_board_config_is_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("config_version = 1\n[camera]\nfps = 'fast'\n")
    _one_line_error(capsys, ["run", "--board", str(bad), "--duration", "1"], "camera.fps", str(bad))
    _one_line_error(capsys, ["run", "--board", "no-such-board"], "no such board")


def test_the_status_line_never_makes_the_frame_loop_wait_for_the_terminal(monkeypatch):
    """The loop's hook only hands over a copy; a terminal that blocks holds up the printing thread only."""
    import threading

    from optitac_edge.cli.commands.run import StatusLine as _StatusLine
    from optitac_edge.core.contact import ContactEstimate

    release, writing = threading.Event(), threading.Event()

    class StuckTerminal:
        def write(self, text):
            writing.set()
            release.wait()  # a terminal nobody reads

        def flush(self):
            pass

    class Stats:
        frames = 0

    monkeypatch.setattr(sys, "stdout", StuckTerminal())
    est, offers = ContactEstimate(), []
    with _StatusLine(0.0, "no link") as line:
        line.offer(est, Stats())
        assert writing.wait(5.0)  # the printing thread is stuck in write()

        def loop():
            for _ in range(1000):
                line.offer(est, Stats())
                offers.append(1)

        frames = threading.Thread(target=loop)
        frames.start()
        frames.join(5.0)
        stuck = frames.is_alive()
        release.set()
    assert not stuck and len(offers) == 1000


def test_the_status_line_fits_an_80_column_terminal_shows_the_true_rate_and_the_link(monkeypatch):
    """Issue 13.14: the line wrapped in 80 columns (leaving a line behind at every refresh), started at
    '1784.2 fps' (frames / time since start, start-up included) and did not say when there was no link."""
    import os
    import shutil
    import threading

    from optitac_edge.cli.commands.run import StatusLine as _StatusLine
    from optitac_edge.core.contact import ContactEstimate

    written, wrote = [], threading.Event()

    class Terminal:
        def write(self, text):
            written.append(text)
            wrote.set()

        def flush(self):
            pass

    class Stats:
        frames = 0

    monkeypatch.setattr(sys, "stdout", Terminal())
    monkeypatch.setattr(shutil, "get_terminal_size", lambda fallback=(80, 24): os.terminal_size((80, 24)))
    now = [0]
    est = ContactEstimate()
    est.contact = True
    est.x_mm, est.y_mm, est.major_mm, est.minor_mm, est.angle_deg, est.strength = -3.25, 4.5, 6.0, 5.5, 45.0, 123.4
    est.shape = "triangle"
    stats = Stats()
    with _StatusLine(0.1, "no link", clock=lambda: now[0]) as line:
        for frames, t_s in ((0, 0.0), (6, 0.1), (12, 0.2)):
            stats.frames, now[0] = frames, int(t_s * 1e9)
            wrote.clear()
            line.offer(est, stats)
            assert wrote.wait(5.0)
    lines = [w.replace("\r\x1b[2K", "") for w in written if w.startswith("\r")]
    assert len(lines) == 3 and all(len(x) <= 79 for x in lines)
    assert lines[0].startswith("[no link]   -.- fps") and lines[1].startswith("[no link]  60.0 fps")
    assert lines[2].startswith("[no link]  60.0 fps") and "CONTACT" in lines[1] and "triangle" in lines[1]


@pytest.mark.parametrize(("argv", "level"), [
    (["run"], "INFO"), (["run", "-v"], "DEBUG"), (["-v", "run"], "DEBUG"), (["run", "-q"], "WARNING"),
    (["replay", "r", "--cal", "c", "-o", "o"], "WARNING"), (["replay", "r", "--cal", "c", "-o", "o", "-v"], "INFO"),
    (["-q", "sim", "out", "--scenario", "rest"], "WARNING"), (["sim", "out", "--scenario", "rest", "-vv"], "DEBUG"),
])
def test_verbosity_works_before_and_after_the_command_and_changes_runs_logging(argv, level):
    import logging

    from optitac_edge.cli import _log_level, build_parser

    assert logging.getLevelName(_log_level(build_parser().parse_args(argv))) == level


def test_no_raw_python_dict_or_list_in_the_lines_a_person_reads(caplog, capsys, tmp_path, rest_rec):
    """Issue 13.14: the calibration logged its report as a Python dict; `calibrate` printed one."""
    import logging

    from optitac_edge.sim.scenarios import write_scenario

    with caplog.at_level(logging.DEBUG):
        assert main(["-vv", "calibrate", "fibers", str(rest_rec), "-o", str(tmp_path / "cal.npz")]) == 0
        seen = write_scenario(tmp_path / "seen", "seen", seed=3, frames=240)
        assert main(["-vv", "calibrate", "centroid", str(seen), "--cal", str(tmp_path / "cal.npz")]) == 0
    lines = [r.getMessage() for r in caplog.records] + capsys.readouterr().out.splitlines()
    assert any("fiber calibration of" in x for x in lines)
    assert not [x for x in lines if "{'" in x or "': " in x or "[0." in x or "], " in x]


def test_the_status_line_rates_one_cameras_frames() -> None:
    """With two cameras the line took its rate from both cameras' counters in turn: -89.7 fps."""
    from types import SimpleNamespace

    from optitac_edge.cli.commands.run import StatusLine as _StatusLine

    now = [0]
    line = _StatusLine(0.1, "no link", clock=lambda: now[0])
    lead, peer = SimpleNamespace(frames=0), SimpleNamespace(frames=0)
    est = SimpleNamespace(copy=lambda: "est")
    rates = []
    for k in range(1, 30):
        now[0] = k * 100_000_000  # a line due at every offer, the two cameras' loops in turn
        lead.frames, peer.frames = 6 * k, 600 + 6 * k
        line.offer(est, peer if k % 2 else lead)
        if line._latest is not None:
            rates.append(line._latest[1])
            line._latest = None
    assert rates[0] is None and len(rates) == 15 and all(r is not None and abs(r - 60.0) < 1e-6 for r in rates[1:])


def test_a_log_record_clears_the_status_line_first() -> None:
    """INFO lines were glued onto the end of the status line."""
    import io
    import logging

    from optitac_edge.io.logs import LIVE_LINE, NonBlockingLogging

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    out = Terminal()
    logs = NonBlockingLogging(logging.INFO, out, logger="optitac_edge.test_live_line", always=True).start()
    LIVE_LINE.active = True
    try:
        out.write("\r\x1b[2K[no link]  60.0 fps  no contact")
        logging.getLogger("optitac_edge.test_live_line").info("first frame processed")
    finally:
        logs.stop()
        LIVE_LINE.active = False
    assert out.getvalue().endswith("no contact\r\x1b[2KINFO optitac_edge.test_live_line: first frame processed\n")


def test_run_says_what_reached_the_mcu_and_what_each_camera_and_sensor_saw(capsys) -> None:
    """run --serial /dev/ttyNOPE reported every frame 'sent'; with two patches on a camera the camera's line
    said more frames with contact than frames (752 frames, 978 with contact)."""
    assert main(["run", "--serial", "/dev/optitac-no-such-port", "--frames", "30"]) == 0
    out = capsys.readouterr().out
    assert "link: 0 messages written" in out and "the port was never open" in out and ", sent " not in out
    assert main(["run", "--board", "sim-hand", "--frames", "30"]) == 0
    out = capsys.readouterr().out.splitlines()
    fingers = next(x for x in out if x.startswith("camera fingers: processed"))
    assert "with contact" not in fingers
    assert any(x.startswith("  sensor 1 'thumb': ") and "with contact" in x for x in out)
    assert "no link: nothing was sent" in out


def _commands(parser, name=""):
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in dict(action.choices).items():
                yield from _commands(sub, f"{name} {sub_name}".strip())
    if name and not any(isinstance(a, argparse._SubParsersAction) for a in parser._actions):
        yield name, parser


def test_every_command_says_what_it_does_with_examples_and_every_option_has_help(capsys) -> None:
    """No subcommand --help had a description or an example; several options had no help text."""
    from optitac_edge.cli import build_parser

    commands = dict(_commands(build_parser()))
    assert len(commands) >= 20
    for name, parser in commands.items():
        assert parser.description and len(parser.description) > 40, name
        assert parser.epilog and parser.epilog.startswith("examples:\n  optitac-edge " + name.split()[0]), name
        for action in parser._actions:
            assert action.help, (name, action.option_strings or action.dest)
    with pytest.raises(SystemExit):
        main(["calibrate", "depth", "--help"])
    out = capsys.readouterr().out
    assert "load cell" in out and "examples:" in out


def test_a_61_fiber_array_is_simulated_mapped_and_oriented_from_its_layout_csv(tmp_path, capsys) -> None:
    """'layout' writes a hexagonal array's CSV; 'sim --layout' simulates that array (its skin and presses
    scaled with its 4 mm pitch), and the calibration steps map, orient and correct it."""
    layout = tmp_path / "hex61.csv"
    assert main(["layout", "--rings", "4", "--pitch-mm", "4", "-o", str(layout)]) == 0
    assert "61 fibers at 4 mm, 32 mm across" in capsys.readouterr().out
    rest, seen, cal = tmp_path / "rest", tmp_path / "seen", tmp_path / "cal.npz"
    for out, scenario, seed in ((rest, "rest", 0), (seen, "seen", 2)):
        assert main(["sim", str(out), "--scenario", scenario, "--seed", str(seed), "--layout", str(layout)]) == 0
    assert main(["calibrate", "fibers", str(rest), "-o", str(cal), "--layout", str(layout)]) == 0
    assert "61/61 fibers found" in capsys.readouterr().out
    truth = Recording(seen).truth
    assert truth is not None and set(truth.size_mm[truth.contact]) == {13.35}  # the 5 mm circle at 4 mm pitch
    assert main(["calibrate", "orientation", str(seen), "--cal", str(cal)]) == 0
    assert main(["calibrate", "centroid", str(seen), "--cal", str(cal)]) == 0
    bundle = load_bundle(cal)
    assert bundle.grid.n == 51 and bundle.thresholds.min_area_mm2 == pytest.approx(16 / 2.25)
    assert max(bundle.extra_meta["centroid_fit"]["heldout_rmse_mm"]) < 0.25 * 4.0  # a quarter pitch


def test_the_status_line_shows_every_sensor_of_a_board_and_labels_the_strength() -> None:
    """Issue 38 item 28: `run` on sim-hand showed one of its three sensors, and an unlabelled 's 9'."""
    from types import SimpleNamespace

    from optitac_edge.cli.commands.run import StatusLine as _StatusLine
    from optitac_edge.core.contact import ContactEstimate

    def est(contact: bool, x: float = 0.0) -> ContactEstimate:
        e = ContactEstimate()
        e.contact, e.x_mm, e.y_mm, e.strength, e.major_mm, e.minor_mm = contact, x, -1.0, 9.0, 3.0, 2.0
        return e

    now = [0]
    line = _StatusLine(0.1, "no link", clock=lambda: now[0])
    stats, other_camera = SimpleNamespace(frames=0), SimpleNamespace(frames=0)
    for k in range(1, 4):
        now[0], stats.frames = k * 100_000_000, 6 * k
        line.offer(est(True, 2.5), stats, "index")
        line.offer(est(False), stats, "middle")
        line.offer(est(True, -4.0), other_camera, "thumb")  # another camera's loop: shown, not rated
        text = line._line()
        if k == 1:
            assert text is not None and "index: +2.5,-1.0 mm strength 9" in text
        else:
            assert text == ("[no link]  60.0 fps  index: +2.5,-1.0 mm strength 9 | middle: - | "
                            "thumb: -4.0,-1.0 mm strength 9")
    single = _StatusLine(0.1, "no link", clock=lambda: now[0])
    single.offer(est(True, 2.5), stats)
    text = single._line()
    assert text is not None and "strength 9" in text and " s 9" not in text
