"""The picamera2 backend against the fake picamera2 (tests/fakes/picamera2)."""

from __future__ import annotations

import subprocess
import sys
import time

import numpy as np
import pytest
from fakes.install import install_picamera2

from optitac_edge.cameras import open_camera
from optitac_edge.errors import CameraError

FAST = {"width": 96, "height": 64, "fps": 200.0, "warmup_frames": 4}


def test_package_import_does_not_import_picamera2():
    code = ("import sys, optitac_edge, optitac_edge.cameras; "
            "assert 'picamera2' not in sys.modules and 'libcamera' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_missing_picamera2_is_a_clear_camera_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "picamera2", None)  # import fails
    with pytest.raises(CameraError, match="apt install python3-picamera2"):
        open_camera("picamera2")


def test_missing_camera(monkeypatch):
    install_picamera2(monkeypatch, cameras=[])
    with pytest.raises(CameraError, match="cannot open camera 0"):
        open_camera("picamera2", **FAST)


@pytest.mark.parametrize("kwargs", [{"width": 95}, {"buffer_count": 2}, {"pixel_format": "rgb"}, {"fps": 0}])
def test_bad_arguments(monkeypatch, kwargs):
    install_picamera2(monkeypatch)
    with pytest.raises(CameraError):
        open_camera("picamera2", **{**FAST, **kwargs})


def test_configured_once_with_lores_yuv420_and_fixed_frame_duration(monkeypatch):
    hw = install_picamera2(monkeypatch)
    with open_camera("picamera2", **FAST, buffer_count=5, controls={"NoiseReductionMode": 0}) as cam:
        for _ in range(5):
            cam.read()
        picam2 = hw.opened[0]
        cfg = picam2.camera_configuration()
        assert picam2.configure_count == 1
        assert cfg["lores"]["format"] == "YUV420" and cfg["lores"]["size"] == (96, 64)
        assert cfg["lores"]["stride"] == 128  # padded rows: the copy must crop them
        assert cfg["buffer_count"] == 5
        assert cfg["controls"]["FrameDurationLimits"] == (5000, 5000)
        assert cfg["controls"]["NoiseReductionMode"] == 0
        assert cam.pixel_format == "gray" and cam.frame_shape == (64, 96)


def test_frames_are_the_y_plane_copied_and_requests_released(monkeypatch):
    hw = install_picamera2(monkeypatch)
    with open_camera("picamera2", **FAST) as cam:
        picam2 = hw.opened[0]
        for _ in range(10):
            c = cam.read()
            np.testing.assert_array_equal(c.frame, hw.produced[c.t_ns])
            # the request went back to libcamera before read() returned: its buffer was
            # recycled (overwritten by the fake) yet our frame is intact
            np.testing.assert_array_equal(c.frame, hw.produced[c.t_ns])
            assert all(r.ref_count == 0 for r in picam2.handed_out)  # released before read() returned
        assert len(picam2.handed_out) == 10
        assert picam2.outstanding_peak <= 3  # queued by picamera2 + being filled: never starved
        assert cam.frame_shape == (64, 96)
    assert len(picam2._free) == 4  # every buffer returned on close


def test_yuv420_frames_are_packed_i420(monkeypatch):
    hw = install_picamera2(monkeypatch)
    with open_camera("picamera2", **FAST, pixel_format="yuv420") as cam:
        c = cam.read()
        assert c.frame.shape == (96, 96)
        np.testing.assert_array_equal(c.frame[:64], hw.produced[c.t_ns])
        assert np.all(c.frame[64:] == 128)  # chroma, padding removed


@pytest.mark.parametrize("new_libcamera", [False, True])
def test_exposure_gain_and_colour_gains_locked_after_warmup(monkeypatch, new_libcamera):
    hw = install_picamera2(monkeypatch, new_libcamera=new_libcamera)
    with open_camera("picamera2", **{**FAST, "warmup_frames": 12}) as cam:
        picam2 = hw.opened[0]
        (lock,) = picam2.set_controls_log
        assert lock == cam.locked_controls
        assert abs(lock["ExposureTime"] - hw.ae_target_us) < 0.01 * hw.ae_target_us  # AE converged
        assert abs(lock["AnalogueGain"] - hw.ae_target_gain) < 0.01
        assert lock["AwbEnable"] is False and len(lock["ColourGains"]) == 2
        if new_libcamera:
            assert lock["ExposureTimeMode"] == 1 and lock["AnalogueGainMode"] == 1 and "AeEnable" not in lock
        else:
            assert lock["AeEnable"] is False
        for _ in range(5):
            cam.read()
        assert picam2._exposure == lock["ExposureTime"]  # the sensor runs at the locked values


def test_given_exposure_is_locked_without_warmup(monkeypatch):
    hw = install_picamera2(monkeypatch)
    with open_camera("picamera2", **FAST, exposure_us=3000, analogue_gain=1.5, colour_gains=(2.0, 1.2)) as cam:
        assert cam.locked_controls["ExposureTime"] == 3000
        assert cam.locked_controls["AnalogueGain"] == 1.5
        assert cam.locked_controls["ColourGains"] == (2.0, 1.2)
        assert hw.opened[0].frames < 8  # no warm-up, only the settle frames


def test_no_lock_leaves_ae_running(monkeypatch):
    hw = install_picamera2(monkeypatch)
    with open_camera("picamera2", **FAST, lock=False) as cam:
        cam.read()
        assert cam.locked_controls == {} and hw.opened[0].set_controls_log == []


def test_sequence_gaps_count_sensor_drops(monkeypatch):
    hw = install_picamera2(monkeypatch)
    with open_camera("picamera2", **FAST) as cam:
        prev = cam.read()
        hw.drop_next = 2
        gaps = 0
        for _ in range(6):
            c = cam.read()
            # seq advances by the frame periods elapsed (5 ms at 200 fps), gaps = lost frames
            assert c.seq - prev.seq == (c.t_ns - prev.t_ns) // 5_000_000
            gaps += c.seq - prev.seq - 1
            prev = c
        assert gaps >= 2 and cam.frames_dropped == gaps


def test_timeout_cancels_the_pending_job_without_leaking(monkeypatch):
    hw = install_picamera2(monkeypatch)
    with open_camera("picamera2", **FAST) as cam:
        picam2 = hw.opened[0]
        cam.read()
        hw.stall = True
        time.sleep(0.02)
        t0 = time.monotonic()
        with pytest.raises(CameraError, match="no frame from the camera within 0.1 s"):
            cam.read(timeout_s=0.1)
        assert time.monotonic() - t0 < 0.3
        assert picam2.cancel_calls == 1 and picam2._job_list == []
        hw.stall = False
        for _ in range(5):
            cam.read()
        time.sleep(0.02)
        assert len(picam2._free) >= 3  # nothing stuck in a cancelled job
    assert picam2.closed_calls == 1


def test_stall_during_warmup_fails_open_and_closes(monkeypatch):
    hw = install_picamera2(monkeypatch, stall=True)
    with pytest.raises(CameraError, match="within"):
        open_camera("picamera2", **FAST, timeout_s=0.1)
    assert hw.opened[0].closed_calls == 1


def test_unadvertised_control_is_a_camera_error(monkeypatch):
    install_picamera2(monkeypatch)
    with pytest.raises(CameraError, match="not advertied"):
        open_camera("picamera2", **FAST, controls={"Sharpness": 0})
