"""Every bad input gets one line and a non-zero exit, never a traceback (issue 13.12)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from optitac_edge.cli import main
from optitac_edge.config import load_board_config
from optitac_edge.core.layout import hex_layout
from optitac_edge.errors import ConfigError, RecordingError
from optitac_edge.io.layout_csv import load_layout_csv
from optitac_edge.io.recording import Recording, RecordingMeta
from optitac_edge.io.recording_writer import RecordingWriter
from optitac_edge.service.wiring import open_board_camera


def _one_line_error(capsys, argv, *needles) -> str:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert "\n" not in err and "Traceback" not in err, err
    for needle in needles:
        assert needle in err, err
    return err


# -- layout CSV ------------------------------------------------------------------------------------

def _layout_rows() -> str:
    lay = hex_layout(rings=2)
    return "".join(f"{i},{x:.4f},{y:.4f}\n" for i, (x, y) in zip(lay.ids, lay.xy_mm))


def test_a_layout_saved_by_excel_with_a_bom_is_accepted(tmp_path):
    path = tmp_path / "bom.csv"
    path.write_text("fiber,x_mm,y_mm\n" + _layout_rows(), encoding="utf-8-sig")
    assert load_layout_csv(path).n_fibers == 19


@pytest.mark.parametrize(("name", "extra", "message"), [
    ("latin1", b"\xe9t\xe9,1,2\n", "not UTF-8 text"),
    ("huge id", b"100000000000000000000000,50,50\n", "fiber number 100000000000000000000000 outside"),
    ("long field", b"99,1," + b"1" * 200_000 + b"\n", "not a CSV layout (field larger than field limit"),
    ("same position", b"99,0.0000,0.0000\n", "two fibers at the same position"),
])
def test_a_bad_layout_csv_is_one_line(tmp_path, capsys, rest_rec, name, extra, message):
    path = tmp_path / "layout.csv"
    path.write_bytes(b"fiber,x_mm,y_mm\n" + _layout_rows().encode() + extra)
    with pytest.raises(ConfigError, match=re.escape(message)):
        load_layout_csv(path)
    _one_line_error(capsys, ["calibrate", "fibers", str(rest_rec), "-o", str(tmp_path / "c.npz"),
                             "--layout", str(path)], message)


# -- recordings -------------------------------------------------------------------------------------

def _recording(tmp_path, n=12) -> object:
    path = tmp_path / "rec"
    with RecordingWriter(path, n, (48, 64), RecordingMeta(rest_frames=5, fps=30.0), with_truth=True) as w:
        for i in range(n):
            w.write(i, np.full((48, 64), 120, np.uint8))
            w.write_truth(i, None)
    return path


@pytest.mark.parametrize(("text", "message"), [
    ('{"rest_frames": 5, "fps": 1e-300}', "'fps' must be a number in 0.1..10000"),
    ('[' * 100_000 + ']' * 100_000, "nested too deeply"),
    ('{"rest_frames": ' + "9" * 5000 + ', "fps": 30}', "garbled meta.json"),
    ('{"rest_frames": 5, "fps": NaN}', "'fps' must be a number"),
])
def test_a_bad_meta_json_is_one_line(tmp_path, capsys, bundle_path, text, message):
    path = _recording(tmp_path)
    (path / "meta.json").write_text(text)
    with pytest.raises(RecordingError, match=message):
        Recording(path)
    _one_line_error(capsys, ["replay", str(path), "--cal", str(bundle_path), "-o", str(tmp_path / "c.csv")],
                    message)


def test_frames_whose_header_claims_a_huge_shape_are_refused(tmp_path, capsys):
    path = _recording(tmp_path)
    with (path / "frames.npy").open("r+b") as f:  # claim 10**12 frames in the header
        np.lib.format.write_array_header_1_0(f, {"descr": "|u1", "fortran_order": False,
                                                 "shape": (10**12, 48, 64)})
    with pytest.raises(RecordingError, match="garbled or truncated frames"):
        Recording(path)


@pytest.mark.parametrize(("rows", "message"), [
    ([], "no rows after the header"),
    (["0,0,,,,,,", "0,0,,,,,,"], "frame 0 is listed twice"),
    (["0,1,circle,,,,5.0,3.0"], "a contact without x_mm, y_mm"),
])
def test_a_bad_truth_csv_is_one_line(tmp_path, capsys, bundle_path, rows, message):
    path = _recording(tmp_path)
    (path / "truth.csv").write_text("frame,contact,shape,x_mm,y_mm,angle_deg,size_mm,depth_mm\n"
                                    + "".join(r + "\n" for r in rows))
    with pytest.raises(RecordingError, match=message):
        Recording(path)
    _one_line_error(capsys, ["evaluate", str(path), "--cal", str(bundle_path)], message)


# -- board config -------------------------------------------------------------------------------------

@pytest.mark.parametrize(("options", "message"), [
    ("width = 1", "camera.options.width: set it with the camera key that does (camera.width)"),
    ("fps = 0", "camera.options.fps: set it with the camera key that does (camera.fps)"),
    ("bogus = 3", "camera.options.bogus: not an option of the sim camera"),
    ("clock = 3", "camera.options.clock: not an option of the sim camera"),
])
def test_camera_options_cannot_bypass_the_checked_keys_or_be_unknown(tmp_path, capsys, options, message):
    board = tmp_path / "b.toml"
    board.write_text(f"[camera]\nbackend = 'sim'\n[camera.options]\n{options}\n")
    with pytest.raises(ConfigError, match=re.escape(message)):
        open_board_camera(load_board_config(board, env={}))
    _one_line_error(capsys, ["run", "--board", str(board), "--frames", "3"], str(board), message)


def test_rest_frames_are_bounded(tmp_path, capsys):
    board = tmp_path / "b.toml"
    board.write_text("[calibration]\nrest_frames = 10000\n")
    _one_line_error(capsys, ["run", "--board", str(board)], "calibration.rest_frames", "1..300")


@pytest.mark.parametrize("url", ["foo://x", "loop://?logging=bogus"])
def test_a_bad_serial_url_is_one_line(capsys, url):
    _one_line_error(capsys, ["run", "--serial", url, "--frames", "3"], "not a valid device or URL")


# -- command-line values ---------------------------------------------------------------------------------

@pytest.mark.parametrize(("argv", "message"), [
    (["run", "--duration", "inf"], "argument --duration: 'inf' is not a number"),
    (["run", "--frames", "0"], "argument --frames: 0 is outside 1.."),
    (["sim", "x", "--scenario", "rest", "--rotation-deg", "nan"], "argument --rotation-deg: 'nan' is not a number"),
    (["sim", "x", "--scenario", "rest", "--width", "0"], "argument --width: 0 is outside 64..8192"),
    (["sim", "x", "--scenario", "rest", "--dark-fibers", "9999"], "--dark-fibers must be distinct fiber indices"),
    (["sim", "x", "--scenario", "rest", "--variant", "-1"], "argument --variant: -1 is outside"),
    (["sim", "x", "--scenario", "rest", "--frames", "0"], "argument --frames: 0 is outside"),
    (["soak", "--minutes", "nan"], "argument --minutes: 'nan' is not a number"),
    (["bench", "--fps", "0"], "argument --fps: 0 is outside"),
])
def test_bad_command_line_values_are_one_line(tmp_path, capsys, argv, message):
    argv = [str(tmp_path / a) if a == "x" else a for a in argv]
    _one_line_error(capsys, argv, message)
    assert not (tmp_path / "x").exists()


def test_the_scenario_names_still_list_in_help_and_errors(capsys):
    err = _one_line_error(capsys, ["sim", "out", "--scenario", "nope"], "invalid choice: 'nope'")
    assert "'rest'" in err and json.dumps("unseen") in err.replace("'", '"')
