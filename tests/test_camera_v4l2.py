"""The v4l2 backend against a fake cv2.VideoCapture (tests/fakes/fake_cv2.py)."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from fakes.install import install_cv2

from optitac_edge.cameras import open_camera
from optitac_edge.cameras.v4l2 import argus_pipeline, fourcc_code
from optitac_edge.errors import CameraError

FAST = {"width": 96, "height": 64, "fps": 200.0}


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


def test_slow_reader_gets_latest_frame_and_counts_drops(monkeypatch):
    dev = install_cv2(monkeypatch)
    with open_camera("v4l2", **FAST) as cam:
        a = cam.read()
        time.sleep(0.05)  # ~10 frames at 200 fps
        b = cam.read()
        assert b.seq - a.seq >= 5
        assert cam.frames_dropped == b.seq - a.seq - 1
        assert cam.overwritten >= 4
        np.testing.assert_array_equal(b.frame, dev.produced[b.t_ns])


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
    with open_camera("v4l2", **FAST) as cam:
        cam.read()
        dev.unplugged = True
        t0 = time.monotonic()
        with pytest.raises(CameraError, match="stopped delivering"):
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


def test_real_opencv_reports_gstreamer_support_honestly():
    from optitac_edge.cameras.v4l2 import has_gstreamer

    assert isinstance(has_gstreamer(), bool)
