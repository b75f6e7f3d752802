"""The contract every camera backend keeps, checked on each (hardware ones against fakes).

* ``open_camera(name, **kwargs)`` opens it; ``pixel_format``, ``height``,
  ``width``, ``fps`` are set and ``frame_shape`` follows from them.
* ``read()`` returns a :class:`CapturedFrame`: a uint8, C-contiguous frame of
  ``frame_shape`` in the declared format, strictly increasing ``t_ns`` (on
  CLOCK_MONOTONIC) and ``seq``.
* A frame is valid until the next ``read()``: backends with
  ``reuses_buffer`` write the next frame into the same memory (and hand it
  out read-only); the others never touch a delivered frame again.
* A source that stops delivering raises :class:`CameraError` within about
  the timeout, never hangs.
* ``close()`` is idempotent, ``read()`` after it raises ``CameraError``, and
  the context manager releases the device.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from fakes.install import install_cv2, install_picamera2

from optitac_edge.core.frames import frame_geometry
from optitac_edge.errors import CameraError
from optitac_edge.io.cameras import CAMERAS, open_camera
from optitac_edge.io.cameras.base import Camera, CapturedFrame
from optitac_edge.io.cameras.frame_ring import MAX_DEPTH
from optitac_edge.io.recording import RecordingMeta
from optitac_edge.io.recording_writer import RecordingWriter


@dataclass
class Setup:
    name: str
    kwargs: dict[str, Any]
    stall: Callable[[bool], None] | None = None  # make the source stop / resume delivering
    released: Callable[[], bool] = lambda: True  # whether the device was given back
    extra: dict[str, Any] = field(default_factory=dict)


def _sim(tmp_path, monkeypatch) -> Setup:
    return Setup("sim", {"fps": 100.0, "realtime": False, "seed": 3})


def _recording(tmp_path, monkeypatch) -> Setup:
    rng = np.random.default_rng(0)
    with RecordingWriter(tmp_path / "rec", 12, (48, 64), RecordingMeta(rest_frames=5, fps=100.0)) as w:
        for i in range(12):
            w.write(i, rng.integers(0, 256, (48, 64), dtype=np.uint8))
    return Setup("recording", {"path": tmp_path / "rec", "loop": True})


def _picamera2(tmp_path, monkeypatch, **hw) -> Setup:
    hardware = install_picamera2(monkeypatch, **hw)
    return Setup(
        "picamera2", {"width": 96, "height": 64, "fps": 200.0, "warmup_frames": 4},
        stall=lambda on: setattr(hardware, "stall", on),
        released=lambda: all(p.closed_calls >= 1 and not p.started for p in hardware.opened),
    )


def _picamera2_yuv(tmp_path, monkeypatch) -> Setup:
    s = _picamera2(tmp_path, monkeypatch, new_libcamera=True)
    s.kwargs["pixel_format"] = "yuv420"
    return s


def _v4l2(tmp_path, monkeypatch, fourcc="GREY") -> Setup:
    dev = install_cv2(monkeypatch, path="/dev/video0")
    return Setup(
        "v4l2", {"device": 0, "width": 96, "height": 64, "fps": 200.0, "fourcc": fourcc},
        stall=lambda on: setattr(dev, "stall", on),
        released=lambda: all(c.release_calls >= 1 for c in dev.opened),
    )


def _v4l2_yuyv(tmp_path, monkeypatch) -> Setup:
    return _v4l2(tmp_path, monkeypatch, fourcc="YUYV")


SETUPS = {"sim": _sim, "recording": _recording, "picamera2": _picamera2,
          "picamera2-yuv420": _picamera2_yuv, "v4l2-grey": _v4l2, "v4l2-yuyv": _v4l2_yuyv}


@pytest.fixture(params=list(SETUPS))
def setup(request, tmp_path, monkeypatch) -> Setup:
    return SETUPS[request.param](tmp_path, monkeypatch)


def test_every_registered_backend_is_covered():
    assert set(CAMERAS) == {s.split("-")[0] for s in SETUPS}


def test_open_announces_geometry(setup):
    with open_camera(setup.name, **setup.kwargs) as cam:
        assert isinstance(cam, Camera)
        assert cam.pixel_format in ("gray", "rgb", "yuv420")
        assert cam.height > 0 and cam.width > 0 and cam.fps > 0
        assert frame_geometry(cam.frame_shape, cam.pixel_format) == (cam.height, cam.width)


def test_frames_follow_the_contract(setup):
    with open_camera(setup.name, **setup.kwargs) as cam:
        last_t = last_seq = None
        for _ in range(8):
            before = time.monotonic_ns()
            captured = cam.read(timeout_s=2.0)
            assert isinstance(captured, CapturedFrame)
            frame = captured.frame
            assert frame.dtype == np.uint8 and frame.flags.c_contiguous
            assert frame.shape == cam.frame_shape
            assert isinstance(captured.t_ns, int) and isinstance(captured.seq, int)
            if last_t is not None:
                assert captured.t_ns > last_t and captured.seq > last_seq
            # CLOCK_MONOTONIC, not some other clock (a few seconds of slack for pacing)
            assert abs(captured.t_ns - before) < 5e9
            last_t, last_seq = captured.t_ns, captured.seq
        assert cam.frames_read == 8


def test_frame_valid_until_next_read(setup):
    with open_camera(setup.name, **setup.kwargs) as cam:
        first = cam.read(timeout_s=2.0)
        kept = first.frame.copy()
        np.testing.assert_array_equal(first.frame, kept)  # untouched while held
        second = cam.read(timeout_s=2.0)
        if cam.reuses_buffer:
            assert not first.frame.flags.writeable and not second.frame.flags.writeable
        else:
            np.testing.assert_array_equal(first.frame, kept)  # never touched again
            assert not np.shares_memory(first.frame, second.frame)


#: Live sources can stall; a simulator and a recording always have the next frame.
STALLABLE = [name for name in SETUPS if not name.startswith(("sim", "recording"))]


@pytest.mark.parametrize("name", STALLABLE)
def test_stalled_source_times_out(name, tmp_path, monkeypatch):
    setup = SETUPS[name](tmp_path, monkeypatch)
    assert setup.stall is not None
    with open_camera(setup.name, **setup.kwargs) as cam:
        cam.read(timeout_s=2.0)
        setup.stall(True)
        # frames already queued for the loop (at most camera.queue_frames) still come first
        for _ in range(MAX_DEPTH + 1):
            t0 = time.monotonic()
            try:
                cam.read(timeout_s=0.15)
            except CameraError as exc:
                assert "within" in str(exc)
                break
        else:
            pytest.fail("a stalled source kept delivering frames")
        assert 0.14 <= time.monotonic() - t0 < 0.6
        setup.stall(False)
        cam.read(timeout_s=2.0)  # recovers when frames come again


def test_close_is_idempotent_and_final(setup):
    cam = open_camera(setup.name, **setup.kwargs)
    cam.read(timeout_s=2.0)
    cam.close()
    cam.close()
    assert cam.closed
    with pytest.raises(CameraError, match="closed"):
        cam.read()
    assert setup.released()


def test_context_manager_releases_device(setup):
    with open_camera(setup.name, **setup.kwargs) as cam:
        cam.read(timeout_s=2.0)
    assert cam.closed
    assert setup.released()


def test_context_manager_releases_on_error(setup):
    with pytest.raises(RuntimeError), open_camera(setup.name, **setup.kwargs) as cam:
        raise RuntimeError("boom")
    assert cam.closed and setup.released()


def test_unknown_backend():
    with pytest.raises(CameraError, match="unknown camera backend"):
        open_camera("nope")
