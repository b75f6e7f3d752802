"""The picamera2 backend against the fake picamera2 (tests/fakes/picamera2).

No test depends on how fast a thread runs: they wait on conditions (with
generous timeouts), and where frames must come in an exact number the fake
delivers them ``paced`` (only while the grab thread waits for one) from a
``budget``.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from fakes.install import install_picamera2

from optitac_edge.errors import CameraError
from optitac_edge.io.cameras import open_camera
from optitac_edge.io.cameras.frame_ring import FrameRing

FAST = {"width": 96, "height": 64, "fps": 200.0, "warmup_frames": 4}
PATIENCE_S = 10.0  # generous: a loaded 2-core CI machine


def _wait_until(condition, what: str, timeout_s: float = PATIENCE_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting until {what}")
        time.sleep(0.002)


def _all_released(hw) -> bool:
    """Every request the fake made went back to it, and nothing was released twice."""
    return not hw.errors and all(p.requests_created == p.requests_freed for p in hw.opened) \
        and all(r.ref_count == 0 for p in hw.opened for r in p.handed_out)


def _quiesce(cam, picam2, hw) -> None:
    """Paced fake: stop delivering, wait until the grab thread waits in vain, empty the ring."""
    with picam2._lock:  # under the lock: no frame is made after this
        hw.budget = 0
    # paced: a frame is only made into a waiting job, so a waiting job means none in flight
    _wait_until(lambda: picam2._job_list, "the grab thread waits for a frame")
    while True:
        try:
            cam.read(timeout_s=0)
        except CameraError:
            return


def test_package_import_does_not_import_picamera2():
    code = ("import sys, optitac_edge, optitac_edge.io.cameras; "
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
            # the request went back to libcamera before the frame was published: its buffer
            # was recycled (overwritten by the fake) yet our frame is intact
            np.testing.assert_array_equal(c.frame, hw.produced[c.t_ns])
            assert not c.frame.flags.writeable
        assert picam2.outstanding_peak <= 3  # queued by picamera2 + held by the thread + being filled
        assert cam.frame_shape == (64, 96)
    assert len(picam2._free) == 4  # every buffer returned on close
    assert _all_released(hw)


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
    install_picamera2(monkeypatch)
    fake = sys.modules["picamera2"]
    captures = []
    capture_metadata = fake.Picamera2.capture_metadata

    def counted(self, *args, **kwargs):
        captures.append(1)
        return capture_metadata(self, *args, **kwargs)

    monkeypatch.setattr(fake.Picamera2, "capture_metadata", counted)
    with open_camera("picamera2", **{**FAST, "warmup_frames": 30}, exposure_us=3000, analogue_gain=1.5,
                     colour_gains=(2.0, 1.2)) as cam:
        assert cam.locked_controls["ExposureTime"] == 3000
        assert cam.locked_controls["AnalogueGain"] == 1.5
        assert cam.locked_controls["ColourGains"] == (2.0, 1.2)
        assert 1 <= len(captures) <= 10  # no warm-up (30), only the settle frames (at most 10)


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


def _read_until_error(cam, timeout_s: float, limit: int = 40) -> tuple[CameraError, float]:
    """Read (frames still queued come first) until read() raises; the error and how long that read took."""
    for _ in range(limit):
        t0 = time.monotonic()
        try:
            cam.read(timeout_s=timeout_s)
        except CameraError as exc:
            return exc, time.monotonic() - t0
    raise AssertionError(f"read() never raised in {limit} reads")


def test_read_timeout_on_a_stall_raises_and_the_camera_recovers(monkeypatch):
    hw = install_picamera2(monkeypatch)
    with open_camera("picamera2", **FAST) as cam:  # grab thread timeout: 2 s
        picam2 = hw.opened[0]
        cam.read()
        hw.stall = True
        exc, took = _read_until_error(cam, 0.1)
        assert str(exc) == "picamera2: no frame from the camera within 0.1 s"
        assert 0.09 <= took < 2.0  # about the timeout (generous upper bound: loaded CI)
        assert picam2.cancel_calls == 0  # the grab thread still waits: the camera is not failed
        hw.stall = False
        last = cam.read(timeout_s=PATIENCE_S)
        for _ in range(5):
            c = cam.read(timeout_s=PATIENCE_S)
            assert c.seq > last.seq
            last = c
    assert picam2.closed_calls == 1 and _all_released(hw) and len(picam2._free) == 4


def test_capture_timeout_in_the_grab_thread_cancels_the_job_and_fails_the_camera(monkeypatch):
    hw = install_picamera2(monkeypatch)
    with open_camera("picamera2", **{**FAST, "timeout_s": 0.3}) as cam:
        picam2 = hw.opened[0]
        cam.read()
        hw.stall = True
        exc, took = _read_until_error(cam, PATIENCE_S)
        assert str(exc) == "picamera2: no frame from the camera within 0.3 s"  # the thread's
        assert took < PATIENCE_S / 2
        assert picam2.cancel_calls == 1 and picam2._job_list == []  # the pending job cancelled
        cam._thread.join(PATIENCE_S)
        assert not cam._thread.is_alive()  # the thread ended; the service reopens the camera
        hw.stall = False
        with pytest.raises(CameraError, match="within 0.3 s"):  # failed for good
            cam.read(timeout_s=0.2)
        assert _all_released(hw)  # nothing stuck in the cancelled job
    assert picam2.closed_calls == 1 and len(picam2._free) == 4


def test_stall_during_warmup_fails_open_and_closes(monkeypatch):
    hw = install_picamera2(monkeypatch, stall=True)
    with pytest.raises(CameraError, match="within"):
        open_camera("picamera2", **FAST, timeout_s=0.1)
    assert hw.opened[0].closed_calls == 1


def test_unadvertised_control_is_a_camera_error(monkeypatch):
    install_picamera2(monkeypatch)
    with pytest.raises(CameraError, match="not advertied"):
        open_camera("picamera2", **FAST, controls={"Sharpness": 0})


# -- the grab thread and its ring ------------------------------------------------------


@pytest.mark.parametrize("queue_frames", [0, 17, -1, 2.5, "4", True, None])
def test_queue_frames_out_of_range_is_a_camera_error_before_opening(monkeypatch, queue_frames):
    hw = install_picamera2(monkeypatch)
    with pytest.raises(CameraError, match=r"picamera2: queue_frames must be an integer 1\.\.16"):
        open_camera("picamera2", **FAST, queue_frames=queue_frames)
    assert hw.opened == []  # the camera was not touched


@pytest.mark.parametrize("pixel_format", ["gray", "yuv420"])
@pytest.mark.parametrize("queue_frames", [1, 4, 16])
def test_a_reader_behind_by_up_to_queue_frames_loses_none(monkeypatch, pixel_format, queue_frames):
    hw = install_picamera2(monkeypatch, paced=True)
    with open_camera("picamera2", **FAST, pixel_format=pixel_format, queue_frames=queue_frames) as cam:
        picam2 = hw.opened[0]
        last = cam.read(timeout_s=PATIENCE_S)
        _quiesce(cam, picam2, hw)
        last_seq, dropped, published = cam._last_seq, cam.frames_dropped, cam._ring.published
        overwritten = cam.overwritten  # the ring may have dropped frames before the first read
        # the loop pauses while queue_frames frames come
        with picam2._lock:
            hw.budget = queue_frames
        _wait_until(lambda: cam._ring.published == published + queue_frames, "the frames are queued")
        _wait_until(lambda: picam2._job_list, "the grab thread waits again")
        seqs = []
        for _ in range(queue_frames):
            c = cam.read(timeout_s=0)  # all there already
            np.testing.assert_array_equal(c.frame[:64], hw.produced[c.t_ns])
            seqs.append(c.seq)
        assert seqs == list(range(last_seq + 1, last_seq + 1 + queue_frames))  # consecutive: none lost
        assert cam.frames_dropped == dropped and cam.overwritten == overwritten
        assert c.t_ns > last.t_ns
        with pytest.raises(CameraError, match="within 0 s"):
            cam.read(timeout_s=0)
    assert _all_released(hw)


@pytest.mark.parametrize("queue_frames", [1, 3])
def test_a_reader_further_behind_drops_the_oldest_and_counts_them(monkeypatch, queue_frames):
    hw = install_picamera2(monkeypatch, paced=True)
    with open_camera("picamera2", **FAST, queue_frames=queue_frames) as cam:
        picam2 = hw.opened[0]
        cam.read(timeout_s=PATIENCE_S)
        _quiesce(cam, picam2, hw)
        last_seq, dropped, published = cam._last_seq, cam.frames_dropped, cam._ring.published
        overwritten = cam.overwritten  # the ring may have dropped frames before the first read
        late = 3  # frames more than the ring holds
        with picam2._lock:
            hw.budget = queue_frames + late
        _wait_until(lambda: cam._ring.published == published + queue_frames + late, "the frames came")
        _wait_until(lambda: picam2._job_list, "the grab thread waits again")
        seqs = [cam.read(timeout_s=0).seq for _ in range(queue_frames)]
        # the newest queue_frames are kept, the oldest `late` dropped and counted
        assert seqs == list(range(last_seq + 1 + late, last_seq + 1 + late + queue_frames))
        assert cam.overwritten == overwritten + late and cam.frames_dropped == dropped + late
    assert _all_released(hw)


@pytest.mark.parametrize("queue_frames", [1, 4])
def test_a_held_frame_is_not_overwritten_until_the_next_read(monkeypatch, queue_frames):
    hw = install_picamera2(monkeypatch, paced=True)
    with open_camera("picamera2", **FAST, queue_frames=queue_frames) as cam:
        held = cam.read(timeout_s=PATIENCE_S)
        kept = held.frame.copy()
        published = cam._ring.published
        # many more frames than the ring has buffers pass while the frame is held
        _wait_until(lambda: cam._ring.published >= published + 3 * (queue_frames + 2), "frames pass")
        assert cam.overwritten > 0
        np.testing.assert_array_equal(held.frame, kept)
        np.testing.assert_array_equal(held.frame, hw.produced[held.t_ns])
        assert not held.frame.flags.writeable
        with pytest.raises(ValueError):
            held.frame[0, 0] = 1
        nxt = cam.read(timeout_s=PATIENCE_S)
        assert nxt.seq > held.seq + 1 and not np.shares_memory(nxt.frame, held.frame)
    assert _all_released(hw)


def test_close_while_the_thread_waits_on_a_stalled_camera(monkeypatch):
    hw = install_picamera2(monkeypatch)
    cam = open_camera("picamera2", **FAST, timeout_s=PATIENCE_S)  # close must not wait the capture out
    picam2 = hw.opened[0]
    cam.read()
    hw.stall = True
    _wait_until(lambda: picam2._job_list, "the grab thread waits for a frame")
    t0 = time.monotonic()
    cam.close()
    assert time.monotonic() - t0 < PATIENCE_S / 2  # the job was cancelled, not waited out
    assert not cam._thread.is_alive()
    assert picam2.cancel_calls >= 1 and picam2._job_list == []
    assert picam2.closed_calls == 1 and not picam2.started
    assert _all_released(hw) and len(picam2._free) == 4
    cam.close()  # idempotent
    assert picam2.closed_calls == 1


def test_close_while_the_thread_copies_waits_for_it_to_release_the_request(monkeypatch):
    hw = install_picamera2(monkeypatch)
    cam = open_camera("picamera2", **FAST)
    picam2 = hw.opened[0]
    cam.read()
    copying, go = threading.Event(), threading.Event()
    copy = cam._copy

    def slow_copy(array, dst):
        copying.set()
        go.wait(PATIENCE_S)
        copy(array, dst)

    cam._copy = slow_copy
    assert copying.wait(PATIENCE_S)  # the thread holds a request
    closer = threading.Thread(target=cam.close)
    closer.start()
    _wait_until(cam._stop.is_set, "close() began")
    assert picam2.started and picam2.closed_calls == 0  # not stopped under the thread's request
    go.set()
    closer.join(PATIENCE_S)
    assert not closer.is_alive() and not cam._thread.is_alive()
    assert picam2.closed_calls == 1 and not picam2.started
    assert _all_released(hw) and len(picam2._free) == 4


def test_close_while_frames_stream_releases_every_request(monkeypatch):
    for pixel_format in ("gray", "yuv420", "gray"):
        hw = install_picamera2(monkeypatch)
        with open_camera("picamera2", **FAST, pixel_format=pixel_format, queue_frames=2) as cam:
            for _ in range(3):
                cam.read(timeout_s=PATIENCE_S)
        assert not cam._thread.is_alive()
        picam2 = hw.opened[0]
        assert picam2.closed_calls == 1 and picam2.cancel_calls >= 1
        assert _all_released(hw) and len(picam2._free) == 4


def test_close_wakes_a_reader_blocked_in_another_thread(monkeypatch):
    hw = install_picamera2(monkeypatch)
    cam = open_camera("picamera2", **FAST)
    cam.read()
    hw.stall = True
    _wait_until(lambda: hw.opened[0]._job_list, "the grab thread waits for a frame")
    while True:  # empty the ring
        try:
            cam.read(timeout_s=0)
        except CameraError:
            break
    errors = []

    def reader():
        try:
            cam.read(timeout_s=PATIENCE_S)
        except CameraError as exc:
            errors.append(exc)

    t = threading.Thread(target=reader)
    t.start()
    cam.close()
    t.join(PATIENCE_S / 2)
    assert not t.is_alive() and len(errors) == 1 and "closed" in str(errors[0])
    assert _all_released(hw)


def test_open_failure_after_the_thread_started_tears_down(monkeypatch):
    hw = install_picamera2(monkeypatch)
    monkeypatch.setattr(FrameRing, "wait_first", lambda self, timeout_s: False)  # no first frame
    with pytest.raises(CameraError, match="picamera2: no frame from the camera within 2 s"):
        open_camera("picamera2", **FAST)
    picam2 = hw.opened[0]
    assert picam2.closed_calls == 1 and not picam2.started
    assert not any(t.name == "picamera2-grab" for t in threading.enumerate())
    assert _all_released(hw)


def test_the_service_passes_camera_queue_frames_from_the_board_config(monkeypatch):
    from optitac_edge.config import load_board_config
    from optitac_edge.service.wiring import open_board_camera

    hw = install_picamera2(monkeypatch)
    cfg = load_board_config("rpi5-gs", env={}, overrides={
        "camera.width": 96, "camera.height": 64, "camera.fps": 200, "camera.warmup_frames": 4,
        "camera.timeout_s": 2.0, "camera.queue_frames": 2})
    with open_board_camera(cfg) as cam:
        assert cam._ring.depth == 2 and cam.pixel_format == "yuv420"
        cam.read(timeout_s=PATIENCE_S)
    assert _all_released(hw)
