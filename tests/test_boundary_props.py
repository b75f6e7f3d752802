"""Generated inputs at every boundary that takes outside bytes (issue 52 §8).

Each test feeds generated input to one boundary and asserts the documented outcome: accepted (a value of the
documented type), or refused in one line with the boundary's own error class; never another exception (a
traceback), never a silently different result. The budget: ``max_examples`` per test below (the suite's CI
runs them all; the sensor process's messages are in tests/test_api_process_replies.py, the wire in
tests/test_protocol_props.py).
"""

from __future__ import annotations

import json
import math
import shutil
import string
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from optitac_edge.errors import BundleError, ConfigError, RecordingError
from optitac_edge.io.rigs.base import GarbledReport

#: Examples per boundary (about a second each on 2 cores).
BUDGET = 120

JSON = st.recursive(st.none() | st.booleans() | st.integers(-2**70, 2**70) | st.floats() | st.text(max_size=6),
                    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner,
                                                                                max_size=4), max_leaves=12)
SLOW = settings(max_examples=BUDGET, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                            HealthCheck.too_slow])


def _one_line(exc: BaseException) -> None:
    text = str(exc)
    assert text and "\n" not in text and "Traceback" not in text, text


@pytest.fixture(scope="module")
def small_rec(tmp_path_factory) -> Path:
    from optitac_edge.sim.optics import CameraOptics
    from optitac_edge.sim.scenarios import write_scenario

    return write_scenario(tmp_path_factory.mktemp("props") / "rec", "unseen", seed=4, frames=40,
                          optics=CameraOptics(width=160, height=120))


def _copy(rec: Path) -> Path:
    out = Path(tempfile.mkdtemp()) / "rec"
    shutil.copytree(rec, out)
    return out


@SLOW
@given(changes=st.dictionaries(st.sampled_from(["rest_frames", "fps", "tares", "simulator", "frame_storage", "x"]),
                               JSON, max_size=3))
def test_meta_json_edits_open_or_are_one_line(small_rec, changes):
    from optitac_edge.io.recording import Recording

    rec = _copy(small_rec)
    try:
        meta = json.loads((rec / "meta.json").read_text())
        meta.update(changes)
        (rec / "meta.json").write_text(json.dumps(meta))
        try:
            opened = Recording(rec)
        except RecordingError as exc:
            _one_line(exc)
            return
        assert 1 <= opened.meta.rest_frames <= len(opened) and math.isfinite(opened.meta.fps) and opened.meta.fps > 0
        for tare in opened.tares:  # every tare within the recording
            assert 1 <= tare.frame < len(opened) and (tare.frames is None or tare.frame + tare.frames <= len(opened))
    finally:
        shutil.rmtree(rec.parent, ignore_errors=True)


CELL = st.one_of(st.text(alphabet=string.printable, max_size=8), st.floats().map(repr), st.integers().map(str))


@SLOW
@given(rows=st.lists(st.lists(CELL, min_size=0, max_size=10), max_size=6), keep_header=st.booleans())
def test_truth_csv_reads_or_is_one_line(small_rec, rows, keep_header):
    from optitac_edge.io.recording import read_truth_file

    text = (small_rec / "truth.csv").read_text().splitlines()
    lines = ([text[0]] if keep_header else []) + [",".join(r) for r in rows] + text[1 + len(rows):]
    try:
        truth, _ = read_truth_file(small_rec / "truth.csv", 40, "\n".join(lines) + "\n")
    except RecordingError as exc:
        _one_line(exc)
        return
    assert len(truth) <= 40 and np.all(truth.frame >= 0) and np.all(truth.frame < 40)
    assert np.all(np.isfinite(truth.x_mm[truth.contact]))


@SLOW
@given(values=st.lists(st.integers(-2**63, 2**63 - 1), min_size=0, max_size=50),
       dtype=st.sampled_from(["<i8", "<f8", "<u8", "<i4"]))
def test_timestamps_read_or_are_one_line(tmp_path_factory, values, dtype):
    from optitac_edge.io.recording import read_timestamps

    path = tmp_path_factory.mktemp("ts") / "timestamps.npy"
    try:
        np.save(path, np.array(values).astype(dtype))
    except OverflowError:
        return
    try:
        t = read_timestamps(path, 40)
    except RecordingError as exc:
        _one_line(exc)
        return
    assert t.dtype == np.int64 and t.shape == (40,) and np.all(np.diff(t) >= 0)


@SLOW
@given(rows=st.lists(st.tuples(st.integers(-5, 2**32), st.floats(), st.floats()), max_size=30),
       header=st.sampled_from(["fiber,x_mm,y_mm", "fiber,x_mm,y_mm,fiducial", "id,x,y", ""]),
       junk=st.text(max_size=20))
def test_layout_csv_loads_or_is_one_line(tmp_path_factory, rows, header, junk):
    from optitac_edge.io.layout_csv import load_layout_csv

    path = tmp_path_factory.mktemp("layout") / "layout.csv"
    extra = ",dark" if header.endswith("fiducial") else ""
    path.write_text(header + "\n" + "".join(f"{i},{x!r},{y!r}{extra}\n" for i, x, y in rows) + junk)
    try:
        layout = load_layout_csv(path)
    except ConfigError as exc:
        _one_line(exc)
        assert str(path) in str(exc)
        return
    assert layout.n_fibers >= 7 and np.all(np.isfinite(layout.xy_mm))
    assert layout.pitch_mm > 0 and len(layout.neighbours()) == layout.n_fibers  # usable: pitch, neighbours


TOML_VALUE = st.one_of(st.integers(-10**6, 10**6).map(str), st.floats(allow_nan=False).map(repr),
                       st.booleans().map(lambda b: str(b).lower()), st.text(string.ascii_letters, max_size=6)
                       .map(json.dumps), st.just("[1, 2]"), st.just("inf"), st.just("nan"))
SECTION_KEYS = {"camera": ["fps", "timeout_s", "backend", "fsp", "width"], "link": ["transport", "rate_divider", "x"],
                "calibration": ["bundle", "rest_frames", "layout", "if_missing"], "watchdog": ["max_frame_gap_s"],
                "rig": ["safe_z", "feed_mm_s"], "nonsense": ["a"]}


@SLOW
@given(entries=st.lists(st.sampled_from(sorted(SECTION_KEYS)).flatmap(
    lambda s: st.tuples(st.just(s), st.sampled_from(SECTION_KEYS[s]), TOML_VALUE)), max_size=5),
    raw=st.text(max_size=30))
def test_board_config_files_load_or_are_one_line(tmp_path_factory, entries, raw):
    from optitac_edge.config import load_board_config

    path = tmp_path_factory.mktemp("board") / "board.toml"
    sections: dict[str, list[str]] = {}
    for section, key, value in entries:
        sections.setdefault(section, []).append(f"{key} = {value}")
    text = "".join(f"[{s}]\n" + "\n".join(dict.fromkeys(lines)) + "\n" for s, lines in sections.items())
    path.write_text(text + (raw if "[" not in raw else ""))
    try:
        config = load_board_config(path, env={})
    except ConfigError as exc:
        _one_line(exc)
        return
    assert config.camera.fps > 0 and math.isfinite(config.camera.timeout_s) and config.camera.timeout_s > 0


@settings(max_examples=BUDGET, deadline=None)
@given(offset=st.integers(0, 10**6), value=st.integers(0, 255), cut=st.booleans())
def test_a_changed_bundle_byte_loads_the_same_or_is_one_line(bundle_bytes, tmp_path_factory, offset, value, cut):
    from optitac_edge.io.bundle_file import load_bundle

    data = bytearray(bundle_bytes)
    offset %= len(data)
    assume(data[offset] != value or cut)
    data = data[:offset] if cut else data[:offset] + bytes([value]) + data[offset + 1:]
    path = tmp_path_factory.mktemp("bundle") / "cal.npz"
    path.write_bytes(bytes(data))
    try:
        bundle = load_bundle(path)
    except BundleError as exc:
        _one_line(exc)
        return
    # a byte zip does not read (a comment, padding) may change; what loads is the same bundle, digest checked
    assert bundle.layout.n_fibers == 217


@pytest.fixture(scope="module")
def bundle_bytes(bundle_path) -> bytes:
    return Path(bundle_path).read_bytes()


def _rig():
    """A GRBL backend with no port: only its report parser is used."""
    from optitac_edge.io.rigs.gcode import GcodeRig

    rig = object.__new__(GcodeRig)
    rig.url, rig._wco, rig._wco_seen, rig._work_positions, rig.report_unit_mm = "test", (1.0, 2.0, 3.0), None, False, 1.0
    return rig


NUM = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(lambda v: f"{v}"),
                st.integers(-10**12, 10**12).map(str), st.text("0123456789.-e+", max_size=8))
FIELD = st.one_of(
    st.tuples(st.sampled_from(["MPos", "WPos", "WCO", "FS", "Bf", "Ov", "Pn", "X"]),
              st.lists(NUM, max_size=4)).map(lambda kv: f"{kv[0]}:{','.join(kv[1])}"),
    st.text(max_size=6))
STATE = st.sampled_from(["Idle", "Run", "Hold:0", "Hold:1", "Door:1", "Alarm", "Jog", "Home", "Check", "Sleep",
                         "Tool", "Idlf", "", "Run:9"])


@settings(max_examples=4 * BUDGET, deadline=None)
@given(state=STATE, fields=st.lists(FIELD, max_size=5), inches=st.booleans())
def test_grbl_reports_parse_or_are_garbled(state, fields, inches):
    """Any status report body: a status with a finite, plausible position in mm, or a GarbledReport (polled
    again); never another exception."""
    from optitac_edge.io.rigs.base import ABSURD_MM

    rig = _rig()
    rig.report_unit_mm = 25.4 if inches else 1.0
    try:
        st_ = rig._parse_status("|".join([state, *fields]))
    except GarbledReport as exc:
        _one_line(exc)
        return
    assert all(math.isfinite(v) and abs(v) < ABSURD_MM for v in st_.xyz_mm)
    positions = [f for f in fields if f.startswith(("MPos:", "WPos:"))]
    assert positions  # a report without a position is garbled


@settings(max_examples=4 * BUDGET, deadline=None)
@given(msg_type=st.integers(0, 255), seq=st.integers(0, 2**16 - 1), payload=st.binary(max_size=64))
def test_mcu_commands_parse_or_are_refused_with_a_result_code(msg_type, seq, payload):
    from optitac_edge.io.protocol.messages import Command, ResultCode
    from optitac_edge.io.protocol.wire import parse_command

    got = parse_command(msg_type, seq, payload)
    if isinstance(got, Command):
        assert got.seq == seq and 1 <= got.rate_divider and got.version in (0, 1, 2, 3)
    else:
        _kind, code = got
        assert isinstance(code, ResultCode) and code != ResultCode.OK


@pytest.fixture(scope="module")
def small_mcap(small_rec, tmp_path_factory) -> tuple[bytes, np.ndarray, np.ndarray]:
    from optitac_edge.io.recording import Recording
    from optitac_edge.io.recording_mcap import recording_to_mcap

    path = recording_to_mcap(Recording(small_rec), tmp_path_factory.mktemp("mcap") / "small.mcap")
    rec = Recording(path)
    return path.read_bytes(), np.array(rec.frames), rec.t_ns.copy()


@settings(max_examples=BUDGET, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(offset=st.integers(0, 10**7), value=st.integers(0, 255), cut=st.booleans())
def test_a_changed_mcap_recording_byte_reads_the_same_or_is_one_line(small_mcap, tmp_path_factory, offset, value,
                                                                    cut):
    """MCAP recordings (record --mcap): a flipped or cut byte anywhere is refused in one line naming the file,
    or reads the very frames, times and metadata (bytes no reader looks at, CRC-checked chunks)."""
    from optitac_edge.io.recording import Recording

    data, frames, t_ns = small_mcap
    raw = bytearray(data)
    offset %= len(raw)
    assume(raw[offset] != value or cut)
    raw = raw[:offset] if cut else raw[:offset] + bytes([value]) + raw[offset + 1:]
    path = tmp_path_factory.mktemp("mcap") / "x.mcap"
    path.write_bytes(bytes(raw))
    try:
        rec = Recording(path)
    except RecordingError as exc:
        _one_line(exc)
        assert str(path) in str(exc)
        return
    assert np.array_equal(rec.frames, frames) and np.array_equal(rec.t_ns, t_ns)


@SLOW
@given(changes=st.dictionaries(st.sampled_from(["rest_frames", "fps", "tares"]),
                               st.one_of(JSON, st.integers(0, 60), st.floats(0.5, 200.0)), max_size=3))
def test_mcap_metadata_edits_open_consistently_or_are_one_line(small_rec, tmp_path_factory, changes):
    """An MCAP recording's metadata edited (its rate, rest frames, tares): opened only when the frames' own
    times and truth agree with it, else one line."""
    from optitac_edge.io.recording import Recording
    from optitac_edge.io.recording_mcap import McapRecordingWriter

    rec = Recording(small_rec)
    path = tmp_path_factory.mktemp("mcap") / "m.mcap"
    try:
        writer = McapRecordingWriter(path, {**rec.meta.to_json(), **changes},
                                     truth_csv=(small_rec / "truth.csv").read_bytes())
    except (TypeError, ValueError):
        return  # not a value JSON holds (the writer is ours: the reader is the boundary)
    with writer:
        for i in range(len(rec)):
            writer.write(i, rec.frame(i), int(rec.t_ns[i]))
    try:
        back = Recording(path)
    except RecordingError as exc:
        _one_line(exc)
        return
    assert back.truth is not None and not back.truth.contact[back.truth.frame < back.meta.rest_frames].any()
    assert abs(np.percentile(np.diff(back.t_ns), 25) * back.meta.fps / 1e9 - 1) <= 0.25
