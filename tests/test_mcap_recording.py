"""Recordings in one MCAP file (frames as sensor_msgs/Image, times, meta, truth): replay, calibrate and
evaluate read them as they read a recording directory."""

from __future__ import annotations

import numpy as np
import pytest

from optitac_edge.cli import main
from optitac_edge.io.recording import Recording
from optitac_edge.io.recording_mcap import recording_to_mcap


@pytest.fixture(scope="module")
def unseen_mcap(unseen_rec, tmp_path_factory):
    return recording_to_mcap(Recording(unseen_rec), tmp_path_factory.mktemp("mcap") / "unseen.mcap")


def test_an_mcap_recording_is_the_directory_it_was_made_from(unseen_rec, unseen_mcap):
    a, b = Recording(unseen_rec), Recording(unseen_mcap)
    np.testing.assert_array_equal(a.frames, b.frames)
    np.testing.assert_array_equal(a.t_ns, b.t_ns)
    assert (a.meta, a.pixel_format) == (b.meta, b.pixel_format)
    assert a.truth is not None and b.truth is not None
    np.testing.assert_array_equal(a.truth.contact, b.truth.contact)
    np.testing.assert_array_equal(a.truth.x_mm, b.truth.x_mm)


def test_replay_and_evaluate_read_it_as_the_directory(unseen_rec, unseen_mcap, bundle_path, tmp_path, capsys):
    for rec, name in ((unseen_rec, "dir.csv"), (unseen_mcap, "mcap.csv")):
        assert main(["replay", str(rec), "--cal", str(bundle_path), "-o", str(tmp_path / name)]) == 0
    assert (tmp_path / "dir.csv").read_text() == (tmp_path / "mcap.csv").read_text()
    capsys.readouterr()
    lines = []
    for rec in (unseen_rec, unseen_mcap):
        main(["evaluate", str(rec), "--cal", str(bundle_path)])
        lines.append(capsys.readouterr().out.splitlines()[1:3])
    assert lines[0] == lines[1] and lines[0][1].startswith("detection: 292/292")  # after the levels line


def test_record_writes_an_mcap_that_calibrates(tmp_path, capsys):
    rec = tmp_path / "bench.mcap"
    assert main(["record", "-o", str(rec), "--frames", "30", "--rest-frames", "10"]) == 0
    assert "wrote" in capsys.readouterr().out and not (tmp_path / "bench.mcap.part").exists()
    r = Recording(rec)
    assert len(r) == 30 and r.meta.rest_frames == 10 and r.truth is None and np.all(np.diff(r.t_ns) > 0)
    assert main(["calibrate", "fibers", str(rec), "-o", str(tmp_path / "cal.npz")]) == 0
    assert "217/217 fibers found" in capsys.readouterr().out


@pytest.mark.parametrize(("content", "message"), [
    (b"garbage\n", "not a readable MCAP recording"),
    (None, "no 'optitac.recording' metadata"),
])
def test_what_is_not_an_mcap_recording_is_refused_in_one_line(tmp_path, capsys, bundle_path, content, message):
    path = tmp_path / "x.mcap"
    if content is None:  # a run's MCAP: contacts, no frames
        assert main(["run", "--frames", "5", "--mcap", str(path)]) == 0
    else:
        path.write_bytes(content)
    capsys.readouterr()
    assert main(["replay", str(path), "--cal", str(bundle_path), "-o", str(tmp_path / "c.csv")]) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_record_mcap_needs_the_mcap_suffix(tmp_path, capsys):
    assert main(["record", "-o", str(tmp_path / "rec"), "--mcap", "--frames", "20"]) == 2
    assert "must end in .mcap" in capsys.readouterr().err


@pytest.mark.parametrize("where", ["frames", "truth"])
def test_a_flipped_byte_is_refused_not_replayed(where, tmp_path, capsys) -> None:
    """Before: a flipped byte in a recording's MCAP replayed silently with a changed angle (mcap's reader
    skips chunk CRCs unless asked, and never checks an attachment's)."""
    from optitac_edge.cli import main

    path = tmp_path / "u.mcap"
    assert main(["sim", str(path), "--scenario", "unseen", "--frames", "30"]) == 0
    data = bytearray(path.read_bytes())
    at = data.find(b"frame,contact") + 200 if where == "truth" else len(data) // 2
    data[at] ^= 0x04
    path.write_bytes(bytes(data))
    capsys.readouterr()
    assert main(["replay", str(path), "--cal", str(tmp_path / "none.npz"), "-o", str(tmp_path / "c.csv")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and ("CRC" in err[0] or "damaged" in err[0] or "readable" in err[0])


def test_frame_times_that_go_backwards_are_refused(tmp_path) -> None:
    """An MCAP recording accepted frame times that go backwards (vibration went negative); a directory's
    timestamps.npy never did."""
    import numpy as np

    from optitac_edge.errors import RecordingError
    from optitac_edge.io.recording import Recording
    from optitac_edge.io.recording_mcap import McapRecordingWriter

    path = tmp_path / "back.mcap"
    times = [0, 33_000_000, 66_000_000, 50_000_000, 99_000_000, 132_000_000]
    with McapRecordingWriter(path, {"rest_frames": 5, "fps": 30.0}) as w:
        for i, t in enumerate(times):
            w.write(i, np.full((24, 32), 100, np.uint8), t)
    with pytest.raises(RecordingError, match="back.mcap: frame times go backwards at frame 3"):
        Recording(path)
