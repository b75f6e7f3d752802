"""The v4l2 backend against a fake cv2.VideoCapture (tests/fakes/fake_cv2.py)."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
import pytest
from fakes.install import install_cv2

from optitac_edge.errors import CameraError
from optitac_edge.io.cameras import open_camera
from optitac_edge.io.cameras.v4l2 import argus_pipeline, fourcc_code, msec_to_ns

FAST = {"width": 96, "height": 64, "fps": 200.0}


def wait_until(cond: Callable[[], bool], timeout_s: float = 20.0) -> None:
    """Poll ``cond`` until it holds (a generous bound: CI machines can be slow)."""
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.001)


class FrameGate:
    """Lets the fake device deliver a frame only when the test allows one.

    ``VideoCapture.grab()`` first waits for a credit (:meth:`allow`), so the test
    decides how many frames the grab thread publishes while the reader sleeps,
    however slow the machine. Their driver timestamps follow the device's frame
    period, so ``seq`` counts them one by one. :meth:`run_free` ends the gating.
    """

    def __init__(self, monkeypatch) -> None:
        import fake_cv2

        self._credits = threading.Semaphore(0)
        self._free = threading.Event()
        grab = fake_cv2.VideoCapture.grab

        def gated_grab(cap) -> bool:
            while not self._free.is_set():
                if self._credits.acquire(timeout=0.005):
                    break
            return grab(cap)

        monkeypatch.setattr(fake_cv2.VideoCapture, "grab", gated_grab)

    def allow(self, frames: int) -> None:
        for _ in range(frames):
            self._credits.release()

    def run_free(self) -> None:
        self._free.set()


@contextmanager
def gated_camera(monkeypatch, **kwargs) -> Iterator[tuple[object, FrameGate, object]]:
    """(camera, gate, device): a v4l2 camera over the fake whose first frame is published, the
    second not yet allowed."""
    dev = install_cv2(monkeypatch)
    gate = FrameGate(monkeypatch)
    gate.allow(1)  # the frame the camera waits for when it opens
    cam = open_camera("v4l2", **FAST, timestamps="driver", **kwargs)
    try:
        wait_until(lambda: cam._ring.published == 1)
        yield cam, gate, dev
    finally:
        gate.run_free()  # the grab thread must get out of grab() for close()
        cam.close()


def published(cam) -> int:
    return cam._ring.published


def test_device_set_up_raw_manual_exposure_in_order(monkeypatch):
    dev = install_cv2(monkeypatch)
    import fake_cv2 as cv2

    with open_camera("v4l2", device=0, **FAST, fourcc="YUYV", exposure=40, gain=3) as cam:
        cap = dev.opened[0]
        assert cap.api == cv2.CAP_V4L2
        props = [p for p, _ in cap.set_log]
        assert props[0] == cv2.CAP_PROP_FOURCC and cap.set_log[0][1] == fourcc_code("YUYV")
        assert props.index(cv2.CAP_PROP_FRAME_WIDTH) < props.index(cv2.CAP_PROP_FPS)
        assert props.index(cv2.CAP_PROP_AUTO_EXPOSURE) < props.index(cv2.CAP_PROP_EXPOSURE)
        assert cap.convert_rgb == 0 and cap.auto_exposure == 1 and cap.exposure == 40 and cap.gain == 3
        assert cam.settings["exposure"] == 40
        c = cam.read()
        assert c.frame.shape == (64, 96)
        np.testing.assert_array_equal(c.frame, dev.produced[c.t_ns])  # the Y channel of YUYV


def test_unsupported_format_and_size_are_refused(monkeypatch):
    dev = install_cv2(monkeypatch, formats=("YUYV",))
    with pytest.raises(CameraError, match="CAP_PROP_FOURCC"):
        open_camera("v4l2", **FAST, fourcc="GREY")
    with pytest.raises(CameraError, match=r"delivers \d+x\d+ YUYV, not the requested 100x64"):
        open_camera("v4l2", width=100, height=64, fps=200.0, fourcc="YUYV")
    assert all(c.release_calls == 1 for c in dev.opened)


def test_missing_or_busy_device(monkeypatch):
    install_cv2(monkeypatch, busy=True)
    with pytest.raises(CameraError, match="no such camera device"):
        open_camera("v4l2", device="/dev/v4l/by-id/usb-none-video-index0")
    with pytest.raises(CameraError, match="cannot open"):
        open_camera("v4l2", device=0, **FAST)


def test_stable_by_id_path(monkeypatch, tmp_path):
    node = tmp_path / "video7"
    node.touch()
    link = tmp_path / "usb-OptiTac_Cam-video-index0"
    os.symlink(node, link)
    dev = install_cv2(monkeypatch, path=os.path.realpath(node))
    with open_camera("v4l2", device=str(link), **FAST) as cam:
        assert cam.read().frame.shape == (64, 96)
        assert dev.opened[0].source == os.path.realpath(node)


@pytest.mark.parametrize("queue_frames", [None, 1, 2, 16])
def test_slow_reader_loses_no_frames_within_the_queue(monkeypatch, queue_frames):
    depth = 4 if queue_frames is None else queue_frames  # 4 is the default
    kwargs = {} if queue_frames is None else {"queue_frames": queue_frames}
    with gated_camera(monkeypatch, **kwargs) as (cam, gate, dev):
        first = cam.read()
        gate.allow(depth)  # the reader "sleeps" while the grab thread publishes depth frames
        wait_until(lambda: published(cam) == 1 + depth)
        for k in range(1, depth + 1):
            c = cam.read(timeout_s=5.0)
            assert c.seq == first.seq + k
            np.testing.assert_array_equal(c.frame, dev.produced[c.t_ns])
        assert cam.frames_dropped == 0 and cam.overwritten == 0
        assert cam.frames_read == depth + 1
        with pytest.raises(CameraError, match=r"no frame from v4l2 0 within 0\.05 s"):
            cam.read(timeout_s=0.05)  # all taken: nothing is delivered twice


def test_latest_frame_slot_drops_and_counts_older_frames(monkeypatch):
    with gated_camera(monkeypatch, queue_frames=1) as (cam, gate, dev):
        a = cam.read()
        gate.allow(5)
        wait_until(lambda: published(cam) == 6)
        b = cam.read(timeout_s=5.0)
        assert b.seq == a.seq + 5  # the latest; the 4 before it were dropped
        assert cam.frames_dropped == 4 and cam.overwritten == 4
        np.testing.assert_array_equal(b.frame, dev.produced[b.t_ns])


def test_reader_further_behind_than_the_queue_gets_the_newest_frames(monkeypatch):
    with gated_camera(monkeypatch, queue_frames=3) as (cam, gate, _dev):
        a = cam.read()
        gate.allow(10)
        wait_until(lambda: published(cam) == 11)
        seqs = [cam.read(timeout_s=5.0).seq for _ in range(3)]
        assert seqs == [a.seq + 8, a.seq + 9, a.seq + 10]  # the oldest 7 were dropped
        assert cam.frames_dropped == 7 and cam.overwritten == 7


@pytest.mark.parametrize("fourcc", ["GREY", "YUYV"])
@pytest.mark.parametrize("queue_frames", [1, 2, 4])
def test_held_frame_is_not_overwritten_while_grab_thread_runs_ahead(monkeypatch, queue_frames, fourcc):
    with gated_camera(monkeypatch, queue_frames=queue_frames, fourcc=fourcc) as (cam, gate, dev):
        held = cam.read()
        kept = held.frame.copy()
        np.testing.assert_array_equal(kept, dev.produced[held.t_ns])
        ahead = 3 * (queue_frames + 2)  # every other buffer of the ring is written several times
        gate.allow(ahead)
        wait_until(lambda: published(cam) == 1 + ahead)
        assert not held.frame.flags.writeable
        np.testing.assert_array_equal(held.frame, kept)  # untouched until the next read
        nxt = cam.read(timeout_s=5.0)
        assert nxt.seq == held.seq + ahead - queue_frames + 1
        np.testing.assert_array_equal(nxt.frame, dev.produced[nxt.t_ns])
        assert cam.overwritten == ahead - queue_frames


def test_frames_waiting_when_the_device_fails_are_still_delivered(monkeypatch):
    with gated_camera(monkeypatch, queue_frames=4) as (cam, gate, dev):
        a = cam.read()
        gate.allow(3)
        wait_until(lambda: published(cam) == 4)
        dev.unplugged = True
        gate.run_free()
        assert [cam.read(timeout_s=5.0).seq for _ in range(3)] == [a.seq + 1, a.seq + 2, a.seq + 3]
        with pytest.raises(CameraError, match="stopped delivering"):
            cam.read(timeout_s=20.0)


@pytest.mark.parametrize("queue_frames", [0, 17, -1, 2.0, True])
def test_queue_frames_out_of_range_is_refused(monkeypatch, queue_frames):
    dev = install_cv2(monkeypatch)
    with pytest.raises(CameraError, match="queue_frames"):
        open_camera("v4l2", **FAST, queue_frames=queue_frames)
    assert dev.opened == []  # refused before the device was touched


def test_driver_timestamps_and_sensor_drops(monkeypatch):
    dev = install_cv2(monkeypatch)
    with open_camera("v4l2", **FAST) as cam:
        prev = cam.read()
        assert prev.t_ns in dev.produced  # the buffer's CLOCK_MONOTONIC timestamp
        dev.drop_next = 3
        for _ in range(6):
            c = cam.read()
            # seq advances by the frame periods elapsed (5 ms): frames the driver lost show
            assert c.seq - prev.seq == (c.t_ns - prev.t_ns) // 5_000_000
            prev = c
        assert cam.frames_dropped >= 3


def test_foreign_driver_clock_falls_back_to_grab_time(monkeypatch):
    install_cv2(monkeypatch, driver_clock="realtime")
    with open_camera("v4l2", **FAST) as cam:
        before = time.monotonic_ns()
        c = cam.read()
        assert abs(c.t_ns - before) < 1e9


def test_unplugged_device_fails_fast(monkeypatch):
    dev = install_cv2(monkeypatch)
    with open_camera("v4l2", **FAST, queue_frames=1) as cam:
        cam.read()
        dev.unplugged = True
        t0 = time.monotonic()
        with pytest.raises(CameraError, match="stopped delivering"):
            for _ in range(2):  # a frame may still be waiting; the one after it fails
                cam.read(timeout_s=5.0)
        assert time.monotonic() - t0 < 1.0
    assert dev.opened[0].release_calls == 1


def test_gstreamer_missing_is_a_clear_error(monkeypatch):
    install_cv2(monkeypatch)
    with pytest.raises(CameraError, match="no GStreamer support"):
        open_camera("v4l2", csi=True, **FAST)


def test_csi_pipeline_through_gstreamer(monkeypatch):
    install_cv2(monkeypatch)
    import fake_cv2 as cv2

    monkeypatch.setattr(cv2, "BUILD_GSTREAMER", True)
    gst = cv2.add_device(cv2.FakeDevice(path="gstreamer", formats=("GREY",)))
    with open_camera("v4l2", csi=True, sensor_id=1, width=640, height=480, fps=60.0,
                     exposure_ns=2_000_000, gain=2.0) as cam:
        cap = gst.opened[0]
        assert cap.api == cv2.CAP_GSTREAMER and cap.set_log == []
        assert cap.source == cam.pipeline
        assert cam.read().frame.shape == (480, 640)
    assert cap.release_calls == 1


def test_argus_pipeline_string():
    p = argus_pipeline(640, 480, 59.94, sensor_id=1, exposure_ns=5_000_000, gain=4.0)
    assert p.startswith("nvarguscamerasrc sensor-id=1 ")
    assert 'exposuretimerange="5000000 5000000"' in p and 'gainrange="4 4"' in p
    assert "aelock=true" in p and "awblock=true" in p
    assert "framerate=2997/50" in p and "width=640,height=480" in p
    assert p.endswith("nvvidconv ! video/x-raw,format=GRAY8 ! appsink drop=1 max-buffers=1 sync=false")


def test_real_opencv_reports_gstreamer_support_honestly(monkeypatch):
    """What the build says, and what it does: a build that opens a GStreamer pipeline must say it has
    GStreamer (issue 39: the test checked only that a bool came back)."""
    import cv2

    from optitac_edge.io.cameras import v4l2

    opened = cv2.VideoCapture("videotestsrc num-buffers=1 ! videoconvert ! appsink", cv2.CAP_GSTREAMER)
    try:
        assert v4l2.has_gstreamer() or not opened.isOpened()
    finally:
        opened.release()
    for text, has in (("  Video I/O:\n    GStreamer:                   YES (1.20.3)\n", True),
                      ("  Video I/O:\n    GStreamer:                   NO\n", False), ("  Video I/O:\n", False)):
        monkeypatch.setattr(v4l2.cv2, "getBuildInformation", lambda text=text: text)
        assert v4l2.has_gstreamer() is has


@pytest.mark.parametrize("t_us", [67355058851, 8410816565, 8675169542, 1, 0, 86_400_123_456_789, 1_700_000_000_123_456])
def test_driver_timestamp_is_the_drivers_microsecond(t_us):
    # POS_MSEC is the buffer's timeval in ms; int(msec * 1e6) lost a nanosecond on about
    # one frame in seventy (a CI failure: frames no longer matched the driver's timestamps)
    t_ns = t_us * 1000
    assert msec_to_ns(t_ns / 1e6) == t_ns
    assert msec_to_ns(t_us / 1e3) == t_ns  # as OpenCV computes it: sec * 1e3 + usec / 1e3
