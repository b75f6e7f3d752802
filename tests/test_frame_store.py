"""Recordings that fit on the board: the rest frames as they are and each fiber's light after them
(``--storage fibers``), read back so that a bundle calibrated from the recording sees exactly the fiber
light of the raw frames."""

from __future__ import annotations

import numpy as np
import pytest

from optitac_edge.calibration.fibers import calibrate_fibers
from optitac_edge.cli import main
from optitac_edge.core.fiber_table import FiberSampler
from optitac_edge.core.layout import hex_layout
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


def _tampered(pair, tmp_path, edit) -> Recording:
    """A copy of the fiber-sum recording with ``edit(directory)`` applied, opened."""
    import shutil

    rec = tmp_path / "r"
    shutil.rmtree(rec, ignore_errors=True)
    shutil.copytree(pair / "fibers", rec)
    edit(rec)
    return Recording(rec)


def _spots(rec, **changes) -> None:
    with np.load(rec / "spots.npz") as z:
        arrays = {k: np.array(z[k]) for k in z.files}
    arrays.update(changes)
    np.savez(rec / "spots.npz", **arrays)


def test_tampered_fiber_sum_recordings_are_refused_in_one_line(pair, tmp_path) -> None:
    """Each of these replayed without a word (issue 38, item 13): groups that share pixels, rest frames shifted
    7 px (centroids 3.5 mm off) or black (25 false contacts), meta.json's fibers or frame shape that disagree
    with the files, float or 64-bit indices cast silently."""
    with np.load(pair / "fibers" / "spots.npz") as z:
        index, start = np.array(z["pixel_index"]), np.array(z["pixel_start"])
    shared = index.copy()
    shared[start[1]] = index[start[0]]  # fiber 1's first pixel is fiber 0's too
    cases = {
        "share pixels": lambda r: _spots(r, pixel_index=shared),
        "pixel_index must be int32, got float64": lambda r: _spots(r, pixel_index=index.astype(np.float64)),
        "pixel_index must be int32, got int64": lambda r: _spots(r, pixel_index=index.astype(np.int64)),
        "do not start at 0": lambda r: _spots(r, pixel_start=start + 1),
        "the rest frames do not fit the fiber sums": lambda r: np.save(
            r / "rest.npy", np.roll(np.load(r / "rest.npy"), 7, axis=2)),
        "do not fit the fiber sums .*black": lambda r: np.save(r / "rest.npy", np.zeros_like(np.load(r / "rest.npy"))),
    }
    for message, edit in cases.items():
        with pytest.raises(RecordingError, match=message):
            _tampered(pair, tmp_path, edit)

    def meta(r, key, value) -> None:
        import json

        m = json.loads((r / "meta.json").read_text())
        m["frame_storage"][key] = value
        (r / "meta.json").write_text(json.dumps(m))

    with pytest.raises(RecordingError, match=r"meta.json: 200 fibers but spots.npz holds 217"):
        _tampered(pair, tmp_path, lambda r: meta(r, "fibers", 200))
    with pytest.raises(RecordingError, match=r"meta.json: frame_shape \[480, 600\] but the rest frames are"):
        _tampered(pair, tmp_path, lambda r: meta(r, "frame_shape", [480, 600]))
    assert len(_tampered(pair, tmp_path, lambda r: None)) == 90  # untouched: read as before


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


@pytest.fixture(scope="module")
def coloured(tmp_path_factory):
    """Colour-coded fibers (the 'real' physics), RGB, raw and as fiber sums."""
    work = tmp_path_factory.mktemp("colour")
    for name, extra in (("raw", []), ("fibers", ["--storage", "fibers"])):
        assert main(["sim", str(work / name), "--scenario", "unseen", "--seed", "5", "--frames", "40", "--rgb",
                     "--physics", "real", *extra]) == 0
    return Recording(work / "raw"), Recording(work / "fibers")


def test_opencvs_gray_is_the_one_the_colours_are_rebuilt_to() -> None:
    """gray_of and green_for against cv2.cvtColor (the reference the per-frame loop reads RGB with)."""
    import cv2

    from optitac_edge.io.fiber_sums import gray_of, green_for

    rng = np.random.default_rng(0)
    px = rng.integers(0, 256, (20000, 3))
    want = cv2.cvtColor(px.astype(np.uint8).reshape(1, -1, 3), cv2.COLOR_RGB2GRAY).reshape(-1)
    np.testing.assert_array_equal(gray_of(px[:, 0], px[:, 1], px[:, 2]), want)
    g = green_for(want, px[:, 0], px[:, 2])
    fits = (g >= 0) & (g <= 255)
    assert fits.mean() > 0.99 and np.all(g[fits] <= px[fits, 1])  # the smallest such green
    np.testing.assert_array_equal(gray_of(px[fits, 0], g[fits], px[fits, 2]), want[fits])


def test_an_rgb_recording_of_fiber_sums_keeps_each_fibers_colour(coloured) -> None:
    """colours.npy holds each fiber's red, green and blue sums exactly; the frames made from it read every
    fiber's gray exactly and each channel's mean within a quarter of a level, so a colour mix sees the
    colours."""
    raw, fibers = coloured
    table = calibrate_fibers(fibers.rest_frames(), fibers.pixel_format, hex_layout(4, 4.0)).fibers
    assert fibers.frames.exact_for(table)
    colours = np.load(fibers.path / "colours.npy")
    rest = fibers.meta.rest_frames
    assert colours.shape == (len(raw) - rest, table.n_fibers, 3)
    starts, index = table.pixel_start, table.pixel_index.astype(np.intp)
    luma, red = FiberSampler(table), FiberSampler(table, "red")
    a, b = np.zeros(table.n_fibers, np.float32), np.zeros(table.n_fibers, np.float32)
    spread = []
    for i in range(rest, len(raw), 7):
        pixels = raw.frame(i).reshape(-1, 3)[index].astype(np.int64)
        np.testing.assert_array_equal(colours[i - rest], np.add.reduceat(pixels, starts[:-1], axis=0))
        made = fibers.frame(i)
        assert made.shape == raw.frame(i).shape
        np.testing.assert_array_equal(luma.means(raw.frame(i), a), luma.means(made, b))
        mine = np.add.reduceat(made.reshape(-1, 3)[index].astype(np.int64), starts[:-1], axis=0)
        err = np.abs(mine - colours[i - rest]) / table.pixel_count[:, None]
        assert err.max() <= 0.25 and err.mean() < 0.01
        np.testing.assert_allclose(red.means(raw.frame(i), a), red.means(made, b), atol=0.6)
        spread.append(np.ptp(colours[i - rest] / colours[i - rest].sum(axis=1, keepdims=True), axis=0))
    assert np.max(spread) > 0.05  # the fibers are coloured: not gray in three channels


def test_garbled_fiber_colours_are_one_line(coloured, tmp_path) -> None:
    import shutil

    rec = tmp_path / "r"
    shutil.copytree(coloured[1].path, rec)
    np.save(rec / "colours.npy", np.zeros((3, 4, 3), np.uint16))
    with pytest.raises(RecordingError, match="colours.npy: must be uint16 of shape"):
        Recording(rec)
    (rec / "colours.npy").write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(RecordingError, match="colours.npy: garbled or truncated fiber colours"):
        Recording(rec)


def test_fiber_sums_continued_on_a_camera_of_another_frame_size_are_refused(tmp_path) -> None:
    """A fiber-sum recording continued on another camera mixed the two (sums over the wrong pixels: 30 of 120
    rest frames false contacts, 2-4 mm off); raw storage refused it, fiber storage must too."""
    from optitac_edge.io.recording import RecordingMeta
    from optitac_edge.io.recording_writer import RecordingWriter
    from optitac_edge.sim.camera import SimCamera

    camera = SimCamera(realtime=False)
    frames = [camera.read().frame.copy() for _ in range(8)]
    path = tmp_path / "r"
    meta = RecordingMeta(rest_frames=5, fps=30.0)

    def find(rest, fmt):
        return calibrate_fibers(list(rest), fmt).fibers

    with pytest.raises(KeyboardInterrupt), RecordingWriter(path, None, frames[0].shape, meta, storage="fibers",
                                                            find_fibers=find) as w:
        for i, f in enumerate(frames):
            w.write(i, f, i * 33_000_000)
        w.sync()  # as a collection's step ends: the fiber map found and the sums durable
        raise KeyboardInterrupt
    h, w_ = frames[0].shape
    other = (h, w_ + 16)  # a camera of another width: its pixel groups fall elsewhere
    with pytest.raises(RecordingError, match=rf"frames of {h}x{w_}.*this camera's are {h}x{w_ + 16}"):
        RecordingWriter(path, None, other, meta, storage="fibers", find_fibers=find, keep_frames=8,
                        kept_t_ns=np.arange(8, dtype=np.int64) * 33_000_000)


def test_damaged_or_hostile_recording_files_are_one_line(pair, tmp_path) -> None:
    """Issue 38, item 18: spots.npz truncated or flipped raised zipfile.BadZipFile; a 1.2 MB spots.npz that
    inflates to 1.2 GB took 2.4 GB of memory before it was refused; a FIFO in a recording hung replay; sums.npy
    with 0 rows blamed truth.csv."""
    import os
    import zipfile

    def truncate(r) -> None:
        data = (r / "spots.npz").read_bytes()
        (r / "spots.npz").write_bytes(data[: len(data) // 2])

    with pytest.raises(RecordingError, match="spots.npz: garbled fiber pixel groups"):
        _tampered(pair, tmp_path, truncate)

    def bomb(r) -> None:
        with zipfile.ZipFile(r / "spots.npz", "w", zipfile.ZIP_DEFLATED) as z, \
                z.open("pixel_index.npy", "w", force_zip64=True) as f:
            np.lib.format.write_array_header_1_0(f, {"descr": "<i4", "fortran_order": False, "shape": (300 << 20,)})
            zeros = bytes(16 << 20)
            for _ in range(4):  # only the header matters: it is refused before any data is read
                f.write(zeros)

    with pytest.raises(RecordingError, match=r"member 'pixel_index' claims 1200 MiB"):
        _tampered(pair, tmp_path, bomb)

    def fifo(r) -> None:
        (r / "timestamps.npy").unlink()
        os.mkfifo(r / "timestamps.npy")

    with pytest.raises(RecordingError, match="timestamps.npy: not a regular file"):
        _tampered(pair, tmp_path, fifo)

    def no_sums(r) -> None:
        sums = np.load(r / "sums.npy")
        np.save(r / "sums.npy", sums[:0])

    with pytest.raises(RecordingError, match=r"sums.npy: 0 frames after the rest frames where timestamps.npy has"):
        _tampered(pair, tmp_path, no_sums)
