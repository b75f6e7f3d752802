"""Raspberry Pi cameras through picamera2 (libcamera).

The camera is configured once with a small ``lores`` YUV420 stream of the
requested size; its Y plane is the grayscale image of the fiber array.

After the start-up (configure, start, exposure lock) a grab thread takes every
completed request, copies the stream (one copy, cropping any row padding) into
the back buffer of a :class:`~.frame_ring.FrameRing`, hands the request back to
libcamera at once, so the camera never runs out of buffers, and publishes the
frame. picamera2 keeps only the newest completed request, so a frame loop that
read the camera directly lost every frame that came while it paused for more
than one frame period; the ring holds up to ``queue_frames`` frames instead,
and :meth:`read` returns the oldest. When one more comes, the oldest waiting
frame is dropped (counted in :attr:`Picamera2Camera.overwritten`, and a gap in
``seq``).

Exposure, analogue gain and colour gains are locked after a warm-up (the
values AE/AWB converged to, or the ones given), because the pipeline's
baseline is only valid while they stay fixed. See docs/cameras.md.

picamera2 comes with Raspberry Pi OS (``apt install python3-picamera2``), not
from PyPI; it is imported only when this backend is opened.
"""

from __future__ import annotations

import concurrent.futures
import logging
import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from optitac_edge.errors import CameraError
from optitac_edge.io.cameras.base import Camera, CapturedFrame
from optitac_edge.io.cameras.frame_ring import FrameRing
from optitac_edge.io.threads import NamedThread
from optitac_edge.text import fields

if TYPE_CHECKING:
    from optitac_edge.io.cameras.section import CameraConfig
    from optitac_edge.io.device import BoardView

log = logging.getLogger(__name__)

_TIMEOUTS = (TimeoutError, concurrent.futures.TimeoutError)
_MANUAL = 1  # libcamera ExposureTimeModeEnum.Manual / AnalogueGainModeEnum.Manual
#: After cancel_all_and_flush(), how long to wait for the job's fate: a job the event loop
#: already ran is signalled just after it releases its lock, a cancelled one at once.
_LATE_S = 1.0


def _import_picamera2() -> Any:
    try:
        import picamera2
    except ImportError as exc:
        raise CameraError(
            "the picamera2 backend needs picamera2, which is not installed "
            f"({exc}); on Raspberry Pi OS: sudo apt install python3-picamera2 "
            "(in a venv made with --system-site-packages)"
        ) from None
    return picamera2


def _check_settings(pixel_format: str, width: int, height: int, fps: float, buffer_count: int,
                    timeout_s: float) -> None:
    """Refuse settings the camera cannot take, before it is opened (one line naming the setting)."""
    if pixel_format not in ("gray", "yuv420"):
        raise CameraError(f"picamera2: pixel_format must be 'gray' or 'yuv420', not {pixel_format!r}")
    if width <= 0 or height <= 0 or width % 2 or height % 2:
        raise CameraError(f"picamera2: frame size must be positive and even, not {width}x{height}")
    if not fps > 0:
        raise CameraError(f"picamera2: fps must be > 0, not {fps}")
    if buffer_count < 3:
        raise CameraError(f"picamera2: buffer_count must be >= 3, not {buffer_count}")
    if not timeout_s > 0:
        raise CameraError(f"picamera2: timeout_s must be > 0, not {timeout_s}")


class Picamera2Camera(Camera):
    """A Raspberry Pi camera (libcamera) read through picamera2.

    Parameters
    ----------
    camera_num : int or str
        Camera index or libcamera camera id (``Picamera2.global_camera_info()``).
    width, height : int
        Size of the delivered frames (the ``lores`` stream); even numbers.
    fps : float
        Frame rate, fixed through ``FrameDurationLimits`` (min = max).
    pixel_format : {"gray", "yuv420"}
        ``gray``: the Y plane, (H, W) — the default, smallest copy.
        ``yuv420``: planar I420, (H*3/2, W), chroma included.
    main_size : (int, int), optional
        Size of the ``main`` stream (default: the frame size). It steers
        libcamera's choice of sensor mode; ``sensor`` chooses it outright.
    sensor : dict, optional
        Passed as ``sensor=`` to ``create_video_configuration``
        (e.g. ``{"output_size": (1332, 990), "bit_depth": 10}``).
    buffer_count : int
        libcamera buffers (>= 3).
    lock : bool
        Lock exposure, gain and colour gains after the warm-up (default). Off
        only for bench work: with AE/AWB running the baseline drifts.
    exposure_us, analogue_gain : optional
        Fixed values to lock; the converged AE values when not given.
    colour_gains : (float, float), optional
        Fixed (red, blue) gains to lock; the converged AWB values when not given.
    warmup_frames : int
        Frames AE/AWB run before their values are read (skipped when all
        three of exposure, gain and colour gains are given).
    settle_frames : int
        At most this many frames are discarded after locking, until the
        metadata shows the locked values.
    controls : dict, optional
        Extra libcamera controls for the configuration (e.g. ``ScalerCrop``,
        ``NoiseReductionMode``); must be advertised by the camera.
    tuning : str or dict, optional
        Tuning file passed to ``Picamera2``.
    timeout_s : float
        Timeout of each capture, during start-up and in the grab thread: a
        camera that delivers nothing for this long has failed (every later
        :meth:`read` raises; close and reopen it).
    queue_frames : int
        Frames that may wait for :meth:`read`, 1..16; when one more comes the
        oldest is dropped. 1 keeps only the latest frame.
    """

    reuses_buffer = True

    @classmethod
    def section_kwargs(cls, section: CameraConfig, board: BoardView) -> dict[str, Any]:
        """``[camera]`` width, height, fps, index, pixel_format, exposure_us, gain, warmup_frames, timeout_s,
        queue_frames."""
        c = section
        return {"width": c.width, "height": c.height, "fps": c.fps, "camera_num": c.index,
                "pixel_format": c.pixel_format, "exposure_us": c.exposure_us or None, "analogue_gain": c.gain or None,
                "warmup_frames": c.warmup_frames, "timeout_s": c.timeout_s, "queue_frames": c.queue_frames}

    def __init__(  # noqa: PLR0913
        self,
        camera_num: int | str = 0,
        width: int = 640,
        height: int = 480,
        fps: float = 60.0,
        pixel_format: str = "gray",
        main_size: tuple[int, int] | None = None,
        sensor: dict[str, Any] | None = None,
        buffer_count: int = 4,
        lock: bool = True,
        exposure_us: int | None = None,
        analogue_gain: float | None = None,
        colour_gains: tuple[float, float] | None = None,
        warmup_frames: int = 30,
        settle_frames: int = 10,
        controls: dict[str, Any] | None = None,
        tuning: str | dict[str, Any] | None = None,
        timeout_s: float = 2.0,
        queue_frames: int = 4,
    ) -> None:
        super().__init__()
        _check_settings(pixel_format, width, height, fps, buffer_count, timeout_s)
        self.pixel_format = pixel_format
        self.width, self.height, self.fps = int(width), int(height), float(fps)
        self._period_ns = 1e9 / self.fps
        self._timeout_s = float(timeout_s)
        self._seq = 0
        self._last_t: int | None = None
        #: Controls locked after the warm-up (empty when ``lock`` is False).
        self.locked_controls: dict[str, Any] = {}
        try:  # before the camera is opened: a bad queue_frames raises without touching it
            self._ring = FrameRing(self.frame_shape, queue_frames)
        except CameraError as exc:
            raise CameraError(f"picamera2: {exc}") from None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

        module = _import_picamera2()
        self._mapped_array = module.MappedArray
        try:
            self._picam2 = module.Picamera2(camera_num, tuning=tuning) if tuning is not None \
                else module.Picamera2(camera_num)
        except Exception as exc:  # noqa: BLE001 - picamera2 raises RuntimeError / IndexError for a missing camera
            raise CameraError(f"picamera2: cannot open camera {camera_num!r}: {exc}") from None
        try:
            self._configure(main_size, sensor, buffer_count, controls or {})
            self._picam2.start()
            if lock:
                self._lock_controls(exposure_us, analogue_gain, colour_gains, warmup_frames,
                                    settle_frames, timeout_s)
            self._thread = NamedThread(target=self._grab_loop, name="picamera2-grab", daemon=True)
            self._thread.start()
            # the first frame proves the grab thread runs (with lock=False nothing captured yet)
            if not self._ring.wait_first(self._timeout_s):
                raise CameraError(f"picamera2: no frame from the camera within {self._timeout_s:.3g} s")
            if self._ring.published == 0:
                raise CameraError(self._ring.error or "picamera2: the grab thread ended")
        except BaseException:
            self._stop_thread()
            self._shutdown()
            raise

    # -- setup ---------------------------------------------------------------

    def _configure(self, main_size: tuple[int, int] | None, sensor: dict[str, Any] | None,
                   buffer_count: int, controls: dict[str, Any]) -> None:
        picam2 = self._picam2
        size = (self.width, self.height)
        period_us = round(1e6 / self.fps)
        kwargs: dict[str, Any] = {
            "main": {"size": tuple(main_size) if main_size else size, "format": "YUV420"},
            "lores": {"size": size, "format": "YUV420"},
            "buffer_count": buffer_count,
            "controls": {"FrameDurationLimits": (period_us, period_us), **controls},
            "display": None,
            "encode": None,
        }
        if sensor:
            kwargs["sensor"] = dict(sensor)
        try:
            picam2.configure(picam2.create_video_configuration(**kwargs))
            stream = picam2.camera_configuration()["lores"]
        except Exception as exc:  # noqa: BLE001 - libcamera's errors, whatever their type, mean "cannot"
            raise CameraError(f"picamera2: cannot configure {self.width}x{self.height} "
                              f"YUV420 at {self.fps:g} fps: {exc}") from None
        got = tuple(int(v) for v in stream["size"])
        if got != size:
            raise CameraError(f"picamera2: the camera delivers {got[0]}x{got[1]}, not the requested "
                              f"{self.width}x{self.height}; configure that size instead")
        self._stride = int(stream["stride"])
        if self._stride < self.width or self._stride % 2:
            raise CameraError(f"picamera2: unexpected lores stride {self._stride}")

    def _lock_controls(self, exposure_us: int | None, analogue_gain: float | None,
                       colour_gains: tuple[float, float] | None, warmup_frames: int,
                       settle_frames: int, timeout_s: float) -> None:
        picam2 = self._picam2
        available = picam2.camera_controls
        md: dict[str, Any] = {}
        if exposure_us is None or analogue_gain is None or colour_gains is None:
            for _ in range(max(warmup_frames, 1)):
                md = self._capture_metadata(timeout_s)
        exposure = int(exposure_us if exposure_us is not None else md["ExposureTime"])
        gain = float(analogue_gain if analogue_gain is not None else md["AnalogueGain"])
        gains = colour_gains if colour_gains is not None else md.get("ColourGains")
        lock: dict[str, Any] = {"ExposureTime": exposure, "AnalogueGain": gain}
        if "AeEnable" in available:  # libcamera < 0.5
            lock["AeEnable"] = False
        for mode in ("ExposureTimeMode", "AnalogueGainMode"):  # libcamera >= 0.5
            if mode in available:
                lock[mode] = _MANUAL
        if gains is not None and "ColourGains" in available:
            lock["ColourGains"] = (float(gains[0]), float(gains[1]))
            if "AwbEnable" in available:
                lock["AwbEnable"] = False
        try:
            picam2.set_controls(lock)
        except Exception as exc:  # noqa: BLE001 - RuntimeError for an unadvertised control, or libcamera's
            raise CameraError(f"picamera2: cannot lock exposure/gain ({exc})") from None
        self.locked_controls = lock
        for _ in range(settle_frames):
            md = self._capture_metadata(timeout_s)
            if (abs(md.get("ExposureTime", exposure) - exposure) <= max(0.02 * exposure, 50)
                    and abs(md.get("AnalogueGain", gain) - gain) <= 0.02 * gain):
                break
        else:
            log.warning("picamera2: exposure/gain did not settle to %s within %d frames "
                        "(last: ExposureTime %s, AnalogueGain %s)", fields(lock), settle_frames,
                        md.get("ExposureTime"), md.get("AnalogueGain"))
        log.info("picamera2: locked %s", fields(lock))

    # -- capture -------------------------------------------------------------

    def _wait(self, job: Any, timeout_s: float, what: str) -> Any:
        """Result of a picamera2 job, or CameraError after ``timeout_s`` (the job cancelled)."""
        try:
            return self._picam2.wait(job, timeout=timeout_s)
        except _TIMEOUTS:
            pass
        except Exception as exc:  # noqa: BLE001 - the job's own error, or CancelledError: close() flushed it
            raise CameraError(f"picamera2: capture failed: {exc or type(exc).__name__}") from None
        # Timed out: drop the pending job so it cannot grab (and leak) a request later.
        self._cancel(job)
        raise CameraError(f"picamera2: no {what} from the camera within {timeout_s:.3g} s")

    def _cancel(self, job: Any) -> None:
        """Cancel the pending jobs; release the request if ``job`` got one all the same."""
        picam2 = self._picam2
        try:
            picam2.cancel_all_and_flush()
        except Exception as exc:  # noqa: BLE001 - failing anyway; keep going
            log.warning("picamera2: cancel_all_and_flush failed: %s", exc)
        try:  # the event loop may have run the job just before the cancel
            late = picam2.wait(job, timeout=_LATE_S)
        except Exception:  # noqa: BLE001 - cancelled (or never finished)
            late = None
        if late is not None and hasattr(late, "release"):
            late.release()

    def _capture_metadata(self, timeout_s: float) -> dict[str, Any]:
        return self._wait(self._picam2.capture_metadata(wait=False), timeout_s, "frame metadata")

    # -- grab thread ---------------------------------------------------------

    def _grab_loop(self) -> None:
        picam2, ring, stop = self._picam2, self._ring, self._stop
        try:
            while not stop.is_set():
                job = picam2.capture_request(wait=False)
                if stop.is_set():  # close() may have flushed before this job existed
                    self._cancel(job)
                    return
                try:
                    request = self._wait(job, self._timeout_s, "frame")
                except CameraError as exc:
                    if not stop.is_set():
                        ring.fail(str(exc))
                    return
                try:
                    md = request.get_metadata()
                    with self._mapped_array(request, "lores", write=False) as mapped:
                        self._copy(mapped.array, ring.back)
                finally:
                    request.release()  # back to libcamera before the frame is published
                t_ns = int(md.get("SensorTimestamp") or time.monotonic_ns())
                self._seq = self._next_seq(md, t_ns)
                self._last_t = t_ns
                ring.publish(t_ns, self._seq)
        except CameraError as exc:
            ring.fail(str(exc))
        except Exception as exc:  # noqa: BLE001 - picamera2 errors must not end the thread silently
            ring.fail(f"picamera2: cannot read the frame: {exc}")

    def _copy(self, array: np.ndarray, dst: np.ndarray) -> None:
        """Copy the (H*3/2, stride) lores buffer into ``dst`` (a ring buffer), without padding."""
        h, w, stride = self.height, self.width, self._stride
        if array.shape != (h * 3 // 2, stride):
            raise CameraError(f"picamera2: lores buffer is {array.shape}, expected {(h * 3 // 2, stride)}")
        if self.pixel_format == "gray":
            np.copyto(dst, array[:h, :w])
        elif stride == w:
            np.copyto(dst, array)
        else:  # chroma planes have stride / 2: copy plane by plane, into the I420 planes of dst
            flat, dst_flat = array.reshape(-1), dst.reshape(-1)
            ch, cs, cw = h // 2, stride // 2, w // 2
            u0, v0 = h * stride, h * stride + ch * cs
            np.copyto(dst[:h], array[:h, :w])
            np.copyto(dst_flat[h * w:h * w + ch * cw].reshape(ch, cw), flat[u0:u0 + ch * cs].reshape(ch, cs)[:, :cw])
            np.copyto(dst_flat[h * w + ch * cw:].reshape(ch, cw), flat[v0:v0 + ch * cs].reshape(ch, cs)[:, :cw])

    def _next_seq(self, md: dict[str, Any], t_ns: int) -> int:
        """Sequence number: the sensor's if reported, else counted from the frame period."""
        if "SensorSequence" in md:
            return int(md["SensorSequence"])
        if self._last_t is None:
            return self._seq + 1
        period = float(md.get("FrameDuration") or 0) * 1000.0 or self._period_ns
        return self._seq + max(1, round((t_ns - self._last_t) / period))

    # -- camera interface ----------------------------------------------------

    @property
    def overwritten(self) -> int:
        """Frames dropped from the ring because ``queue_frames`` newer ones were waiting."""
        return self._ring.overwritten

    def _read_internal(self, timeout_s: float) -> CapturedFrame:
        try:
            frame, t_ns, seq = self._ring.take(timeout_s, "the camera")
        except CameraError as exc:
            message = str(exc)
            if not message.startswith("picamera2:"):
                message = f"picamera2: {message}"
            raise CameraError(message) from None
        return CapturedFrame(frame, t_ns, seq)

    # -- teardown ------------------------------------------------------------

    def _stop_thread(self) -> None:
        """End the grab thread; it releases any request it holds before it returns."""
        self._stop.set()
        thread = self._thread
        if thread is None:
            return
        try:  # ends a wait for the next frame at once
            self._picam2.cancel_all_and_flush()
        except Exception as exc:  # noqa: BLE001 - closing anyway
            log.warning("picamera2: cancel_all_and_flush failed: %s", exc)
        thread.join(timeout=self._timeout_s + _LATE_S + 1.0)
        if thread.is_alive():
            log.warning("picamera2: grab thread did not end; stopping the camera anyway")

    def _shutdown(self) -> None:
        picam2 = self._picam2
        for step in ("cancel_all_and_flush", "stop", "close"):
            try:
                getattr(picam2, step)()
            except Exception as exc:  # noqa: BLE001 - keep tearing down
                log.warning("picamera2: %s failed: %s", step, exc)

    def _close_internal(self) -> None:
        self._stop_thread()
        self._shutdown()
        self._ring.fail("picamera2: camera is closed")  # wakes a read() blocked in another thread
