"""Recordings that fit on the board: the rest frames as they are and each fiber's light after them
(``--storage fibers``), read back so that a bundle calibrated from the recording sees exactly the fiber
light of the raw frames."""

from __future__ import annotations

import numpy as np
import pytest

from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.cli import main
from optitac_edge.core.fiber_table import FiberSampler
from optitac_edge.errors import RecordingError
from optitac_edge.io.recording import Recording


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """The same simulated presses, raw and as fiber sums (gray and RGB)."""
    work = tmp_path_factory.mktemp("storage")
    for name, extra in (("raw", []), ("fibers", ["--storage", "fibers"]), ("rgb-raw", ["--rgb"]),
                        ("rgb-fibers", ["--rgb", "--storage", "fibers"])):
        assert main(["sim", str(work / name), "--scenario", "unseen", "--seed", "3", "--frames", "90", *extra]) == 0
    return work


@pytest.mark.parametrize("kind", ["", "rgb-"])
def test_every_fiber_reads_the_raw_frames_light_exactly(pair, kind) -> None:
    raw, fibers = Recording(pair / f"{kind}raw"), Recording(pair / f"{kind}fibers")
    assert len(raw) == len(fibers) and raw.frame_shape == fibers.frame_shape
    assert raw.pixel_format == fibers.pixel_format and np.array_equal(raw.t_ns, fibers.t_ns)
    np.testing.assert_array_equal(np.asarray(raw.rest_frames()), np.asarray(fibers.rest_frames()))
    table = calibrate_fibers(fibers.rest_frames(), fibers.pixel_format).fibers
    assert fibers.frames.exact_for(table)
    a, b = FiberSampler(table), FiberSampler(table)
    out_a, out_b = np.zeros(table.n_fibers, np.float32), np.zeros(table.n_fibers, np.float32)
    for i in range(len(raw)):
        np.testing.assert_array_equal(a.means(raw.frame(i), out_a), b.means(fibers.frame(i), out_b))


def test_the_same_contacts_and_figures_from_either_storage(pair, tmp_path, capsys) -> None:
    cal = tmp_path / "cal.npz"
    assert main(["calibrate", "fibers", str(pair / "fibers"), "-o", str(cal)]) == 0
    for name in ("raw", "fibers"):
        assert main(["replay", str(pair / name), "--cal", str(cal), "-o", str(tmp_path / f"{name}.csv")]) == 0
        assert main(["evaluate", str(pair / name), "--cal", str(cal)]) == 0
    assert (tmp_path / "raw.csv").read_bytes() == (tmp_path / "fibers.csv").read_bytes()
    out = capsys.readouterr().out.splitlines()
    figures = [line for line in out if line.startswith(("detection", "centroid"))]
    assert len(figures) == 4 and figures[:2] == figures[2:]


def test_a_recording_of_fiber_sums_is_a_fraction_of_the_raw_one(pair) -> None:
    def size(name: str) -> int:
        return sum(f.stat().st_size for f in (pair / name).iterdir())

    rest = Recording(pair / "fibers").meta.rest_frames
    per_frame_raw = (size("raw") - size("fibers")) / (90 - rest)
    sums = (pair / "fibers" / "sums.npy").stat().st_size
    assert sums <= 128 + (90 - rest) * 217 * 2  # uint16 a fiber a frame
    assert per_frame_raw > 300_000


def test_a_frame_made_from_sums_looks_like_the_raw_frame(pair) -> None:
    """Beyond the fiber pixels (what a fiber map found elsewhere may read), the frame follows the fibers'
    light: within a few gray levels of the raw frame where the fibers are."""
    raw, fibers = Recording(pair / "raw"), Recording(pair / "fibers")
    lit = np.asarray(raw.rest_frames()).mean(axis=0) > 60
    for i in (40, 60, 85):
        d = np.abs(raw.frame(i).astype(int) - fibers.frame(i).astype(int))[lit]
        assert np.median(d) <= 3


def test_garbled_fiber_sums_are_one_line(pair, tmp_path) -> None:
    import shutil

    rec = tmp_path / "r"
    shutil.copytree(pair / "fibers", rec)
    (rec / "sums.npy").write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(RecordingError, match="sums.npy: garbled or truncated fiber sums"):
        Recording(rec)
    shutil.copy(pair / "fibers" / "sums.npy", rec / "sums.npy")
    (rec / "spots.npz").unlink()
    with pytest.raises(RecordingError, match="spots.npz: garbled fiber pixel groups"):
        Recording(rec)
    shutil.copy(pair / "fibers" / "spots.npz", rec / "spots.npz")
    sums = np.load(rec / "sums.npy")
    sums[3, 5] = 65535  # more light than the fiber's pixels can hold
    np.save(rec / "sums.npy", sums)
    with pytest.raises(RecordingError, match="a sum larger than its fiber's pixels can hold"):
        Recording(rec)


def test_record_keeps_fiber_sums_by_default_and_raw_on_request(tmp_path, capsys) -> None:
    assert main(["record", "-o", str(tmp_path / "r"), "--frames", "30"]) == 0
    assert Recording(tmp_path / "r").meta.extra["frame_storage"]["storage"] == "fibers"
    assert not (tmp_path / "r" / "frames.npy").exists()
    assert main(["record", "-o", str(tmp_path / "raw"), "--frames", "30", "--storage", "raw"]) == 0
    assert (tmp_path / "raw" / "frames.npy").exists()
    capsys.readouterr()
    assert main(["record", "-o", str(tmp_path / "m.mcap"), "--frames", "30", "--storage", "fibers"]) == 2
    assert "an MCAP recording holds raw frames" in capsys.readouterr().err


def test_a_collection_continues_in_the_storage_it_began_in(tmp_path, capsys) -> None:
    import signal
    import subprocess
    import sys
    import time

    from optitac_edge.bringup.collect import JOURNAL

    out = tmp_path / "r"
    start = ("import runpy, signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
             "sys.argv = ['optitac-edge', *sys.argv[1:]]; runpy.run_module('optitac_edge.cli', run_name='__main__')")
    proc = subprocess.Popen([sys.executable, "-c", start, "collect", "seen", "--rig", "sim://", "-o", str(out),
                             "--limit", "4"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    while proc.poll() is None and not ((out / JOURNAL).exists() and len((out / JOURNAL).read_text().splitlines()) > 1):
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.communicate(timeout=60)
    assert main(["collect", "seen", "--rig", "sim://", "-o", str(out), "--limit", "4", "--storage", "raw"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "continue it with the same storage" in err[0]
    assert main(["collect", "seen", "--rig", "sim://", "-o", str(out), "--limit", "4"]) == 0
    assert Recording(out).meta.extra["frame_storage"]["storage"] == "fibers"
