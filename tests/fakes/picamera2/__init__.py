"""A fake ``picamera2`` for tests: the real API surface the backend uses, no hardware.

Follows picamera2 0.3.2x: ``Picamera2(camera_num=0, verbose_console=None,
tuning=None)``, ``create_video_configuration(main=, lores=, buffer_count=,
controls=, display=, encode=, sensor=, ...)``, ``configure``,
``camera_configuration()``, ``camera_controls``, ``start``/``stop``/``close``,
``set_controls`` (RuntimeError for controls libcamera does not advertise),
``capture_request(wait=None, signal_function=None, flush=None)`` and
``capture_metadata(wait=None, signal_function=None)`` returning a ``Job``
when ``wait=False``, ``wait(job, timeout=None)`` (``TimeoutError`` from the
job's future), ``cancel_all_and_flush()``, requests with ``get_metadata()``
and ``release()`` (reference counted, buffers recycled on release) and
``MappedArray(request, stream, reshape=True, write=True)`` giving the YUV420
buffer as (H*3/2, stride).

A background thread plays the sensor: one frame per ``FrameDurationLimits``
period, AE/AWB converging while enabled, controls taking effect two frames
after ``set_controls`` (as on the real pipeline). As in picamera2 with
``queue=True``, only the newest completed request waits for the application
(older ones go back to the camera); jobs run in the sensor thread under the
camera lock and are signalled after it is released. Tests steer it through the
module-level :data:`HARDWARE`; ``paced`` and ``budget`` make frame delivery
deterministic for tests, the rest is what real hardware does.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import CancelledError, Future
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["HARDWARE", "FakeHardware", "Job", "MappedArray", "Picamera2", "reset"]


@dataclass
class FakeHardware:
    """What the fake camera system looks like; tests change it before opening."""

    cameras: list[dict[str, Any]] = field(default_factory=lambda: [{"Model": "imx219", "Id": "/base/i2c@0/imx219@10"}])
    new_libcamera: bool = False  # True: ExposureTimeMode/AnalogueGainMode instead of AeEnable
    stride_align: int = 64  # lores row stride alignment in bytes
    stall: bool = False  # no frames complete while True
    drop_next: int = 0  # frames the sensor loses (the timestamp jumps)
    #: Test knob: frames complete only while a job waits for one (an application that
    #: never falls behind the sensor), and the sensor clock advances one period per
    #: frame, so pauses leave no gap in the timestamps. Not something hardware does.
    paced: bool = False
    #: Test knob: frames that may still complete (None: unlimited); at 0 the sensor
    #: delivers nothing, like ``stall``. Change it under ``Picamera2._lock`` for an exact count.
    budget: int | None = None
    ae_target_us: int = 8000
    ae_target_gain: float = 2.5
    awb_target: tuple[float, float] = (1.8, 1.5)
    opened: list[Picamera2] = field(default_factory=list)
    #: (SensorTimestamp, Y plane) of every frame produced, for checking copies.
    produced: dict[int, np.ndarray] = field(default_factory=dict)
    #: Misuse seen by the fake (a request released twice, used after release); tests assert it stays empty.
    errors: list[str] = field(default_factory=list)


HARDWARE = FakeHardware()


def reset() -> FakeHardware:
    global HARDWARE
    HARDWARE = FakeHardware()
    return HARDWARE


def _align(n: int, a: int) -> int:
    return (n + a - 1) // a * a


class Job:
    """picamera2.job.Job: functions run by the event loop, a Future for the result."""

    def __init__(self, functions, signal_function=None) -> None:
        self._functions = list(functions)
        self._future: Future = Future()
        self._future.set_running_or_notify_cancel()
        self._signal_function = signal_function
        self._result = None
        self.calls = 0

    def execute(self) -> bool:
        try:
            while self._functions:
                done, result = self._functions[0]()
                self.calls += 1
                if not done:
                    break
                self._functions.pop(0)
            if not self._functions:
                self._result = result
        except Exception as exc:  # noqa: BLE001 - as picamera2.job.Job: the error goes to the future
            self._future.set_exception(exc)
            self._functions = []
        return not self._functions

    def signal(self) -> None:
        if not self._future.done():
            self._future.set_result(self._result)
        if self._signal_function:
            self._signal_function(self)

    def get_result(self, timeout=None):
        return self._future.result(timeout=timeout)

    def cancel(self) -> None:
        self._future.set_exception(CancelledError())


class CompletedRequest:
    def __init__(self, picam2: Picamera2, buffer: np.ndarray, metadata: dict[str, Any]) -> None:
        self.picam2 = picam2
        self.ref_count = 1
        picam2.requests_created += 1
        self.config = {k: dict(v) if isinstance(v, dict) else v for k, v in picam2.camera_config.items()}
        self._buffer = buffer
        self._metadata = metadata

    def _misuse(self, message: str) -> None:
        self.picam2.hw.errors.append(message)

    def acquire(self) -> None:
        with self.picam2._lock:
            if self.ref_count == 0:
                self._misuse("acquire with ref_count 0")
                raise RuntimeError("CompletedRequest: acquiring lock with ref_count 0")
            self.ref_count += 1

    def release(self) -> None:
        with self.picam2._lock:
            self.ref_count -= 1
            if self.ref_count < 0:
                self._misuse("release with ref_count 0")
                raise RuntimeError("CompletedRequest: lock now has negative ref_count")
            if self.ref_count == 0:
                self._buffer[:] = 0xEE  # the camera writes the next frame into it
                self.picam2._free.append(self._buffer)
                self.picam2.requests_freed += 1
                self._buffer = None  # type: ignore[assignment]
                self._metadata = None  # type: ignore[assignment]

    def get_metadata(self) -> dict[str, Any]:
        if self._metadata is None:
            self._misuse("get_metadata after release")
        assert self._metadata is not None, "request used after release"
        return dict(self._metadata)

    def make_buffer(self, name: str) -> np.ndarray:
        assert name == "lores"
        return self._buffer.copy()


class MappedArray:
    def __init__(self, request: CompletedRequest, stream: str, reshape: bool = True, write: bool = True) -> None:
        self._request, self._stream, self._reshape = request, stream, reshape
        self._array = None

    def __enter__(self) -> MappedArray:  # noqa: PYI034 - Self needs Python 3.11
        buf = self._request._buffer
        if buf is None:
            self._request._misuse("MappedArray on a released request")
        assert buf is not None, "MappedArray on a released request"
        if self._reshape:
            cfg = self._request.config[self._stream]
            assert cfg["format"] in ("YUV420", "YVU420")
            _, h = cfg["size"]
            buf = buf.reshape(h * 3 // 2, cfg["stride"])
        self._array = buf
        return self

    def __exit__(self, *exc) -> None:
        self._array = None

    @property
    def array(self):
        return self._array


_OLD_CONTROLS = ("AeEnable", "AwbEnable", "ExposureTime", "AnalogueGain", "ColourGains",
                 "FrameDurationLimits", "NoiseReductionMode", "ScalerCrop")
_NEW_CONTROLS = ("ExposureTimeMode", "AnalogueGainMode", "AwbEnable", "ExposureTime", "AnalogueGain",
                 "ColourGains", "FrameDurationLimits", "NoiseReductionMode", "ScalerCrop")


class Picamera2:
    """The fake camera; one background thread per started camera."""

    @staticmethod
    def global_camera_info() -> list[dict[str, Any]]:
        return [dict(c) for c in HARDWARE.cameras]

    def __init__(self, camera_num=0, verbose_console=None, tuning=None) -> None:
        cams = HARDWARE.cameras
        if isinstance(camera_num, int):
            if not 0 <= camera_num < len(cams):
                raise IndexError("list index out of range")
        elif not any(c["Id"] == camera_num for c in cams):
            raise RuntimeError("Camera __init__ sequence did not complete.")
        self.hw = HARDWARE
        self.camera_idx = camera_num
        self.tuning = tuning
        self.is_open = True
        self.started = False
        self.camera_config: dict[str, Any] | None = None
        self.configure_count = 0
        self.closed_calls = 0
        self.stopped_calls = 0
        self.cancel_calls = 0
        self.set_controls_log: list[dict[str, Any]] = []
        self._controls: dict[str, Any] = {}
        self._pending: list[tuple[int, dict[str, Any]]] = []  # (frame taking effect, controls)
        self._lock = threading.RLock()
        self._job_list: list[Job] = []
        self.completed_requests: list[CompletedRequest] = []
        self._max_queue_len = 1
        self._free: list[np.ndarray] = []
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.frames = 0
        self.outstanding_peak = 0
        self.handed_out: list[CompletedRequest] = []  # requests given to the application
        self.requests_created = 0  # completed requests made (each holds a buffer) ...
        self.requests_freed = 0  # ... and given back (ref_count down to 0): equal once all are released
        names = _NEW_CONTROLS if self.hw.new_libcamera else _OLD_CONTROLS
        self.camera_controls = {n: (None, None, None) for n in names}
        self._exposure, self._gain, self._cg = 1000, 1.0, (1.0, 1.0)
        self.hw.opened.append(self)

    # configuration
    def create_video_configuration(self, main={}, lores=None, raw={}, transform=None,  # noqa: B006 - picamera2's
                                   colour_space=None, buffer_count=6, controls={},  # noqa: B006 - signature
                                   display="main", encode="main", queue=True, sensor={},  # noqa: B006
                                   use_case="video") -> dict[str, Any]:
        cfg = {"use_case": use_case, "main": {"format": "XBGR8888", "size": (1280, 720), **main},
               "lores": None if lores is None else {"format": "YUV420", "size": (320, 240), **lores},
               "buffer_count": buffer_count, "queue": queue, "display": display, "encode": encode,
               "sensor": dict(sensor),
               "controls": {"NoiseReductionMode": 1, "FrameDurationLimits": (33333, 33333), **controls}}
        return cfg

    def configure(self, camera_config) -> None:
        if self.started:
            raise RuntimeError("Camera must be stopped before configuring")
        cfg = {k: dict(v) if isinstance(v, dict) else v for k, v in camera_config.items()}
        for name in ("main", "lores"):
            s = cfg.get(name)
            if s is None:
                continue
            w, h = s["size"]
            if s["format"] == "YUV420" and (w % 2 or h % 2):
                w, h = w & ~1, h & ~1  # libcamera adjusts invalid sizes
                s["size"] = (w, h)
            s["stride"] = _align(w, self.hw.stride_align) if s["format"] == "YUV420" else _align(w * 4, 64)
            s["framesize"] = s["stride"] * h * 3 // 2 if s["format"] == "YUV420" else s["stride"] * h
        lo, ma = cfg.get("lores"), cfg["main"]
        if lo is not None and (lo["size"][0] > ma["size"][0] or lo["size"][1] > ma["size"][1]):
            raise RuntimeError("lores stream dimensions may not exceed main stream")
        for k in cfg["controls"]:
            if k not in self.camera_controls:
                raise RuntimeError(f"Control {k} is not advertied by libcamera")
        self._controls = dict(cfg["controls"])
        self.camera_config = cfg
        self.configure_count += 1

    def camera_configuration(self) -> dict[str, Any]:
        return self.camera_config  # type: ignore[return-value]

    def set_controls(self, controls) -> None:
        for k in controls:
            if k not in self.camera_controls:
                raise RuntimeError(f"Control {k} is not advertied by libcamera")
        with self._lock:
            self.set_controls_log.append(dict(controls))
            self._pending.append((self.frames + 2, dict(controls)))

    # running
    def start(self, config=None, show_preview=False) -> None:
        if self.camera_config is None:
            raise RuntimeError("Camera has not been configured")
        lo = self.camera_config["lores"]
        n = self.camera_config["buffer_count"]
        self._free = [np.zeros(lo["framesize"], dtype=np.uint8) for _ in range(n)]
        self.started = True
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self.stopped_calls += 1
        if not self.started:
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        self.started = False
        with self._lock:
            for req in self.completed_requests:
                req.release()
            self.completed_requests = []

    def close(self) -> None:
        self.closed_calls += 1
        if self.started:
            self.stop()
        self.is_open = False

    def _auto(self) -> dict[str, Any]:
        c = self._controls
        ae = c.get("AeEnable", True) if "AeEnable" in self.camera_controls else \
            c.get("ExposureTimeMode", 0) != 1
        if ae:
            self._exposure += (self.hw.ae_target_us - self._exposure) // 2
            self._gain += (self.hw.ae_target_gain - self._gain) / 2
        else:
            self._exposure, self._gain = int(c["ExposureTime"]), float(c["AnalogueGain"])
        if c.get("AwbEnable", True) and "ColourGains" not in c:
            t = self.hw.awb_target
            self._cg = ((self._cg[0] + t[0]) / 2, (self._cg[1] + t[1]) / 2)
        elif "ColourGains" in c:
            self._cg = tuple(c["ColourGains"])
        return {"ExposureTime": int(self._exposure), "AnalogueGain": float(self._gain),
                "DigitalGain": 1.0, "ColourGains": tuple(self._cg)}

    def _run(self) -> None:
        period_ns = int(self.camera_config["controls"]["FrameDurationLimits"][0]) * 1000  # type: ignore[index]
        lo = self.camera_config["lores"]  # type: ignore[index]
        (w, h), stride = lo["size"], lo["stride"]
        next_ns = time.monotonic_ns() + period_ns
        last_t = time.monotonic_ns()  # the sensor clock of paced mode
        while not self._stop.is_set():
            delay = (next_ns - time.monotonic_ns()) / 1e9
            if delay > 0:
                time.sleep(delay)
            t = next_ns
            next_ns += period_ns
            if self.hw.stall:
                continue
            with self._lock:
                if self.hw.budget == 0 or (self.hw.paced and not self._job_list):
                    continue
                if self.hw.paced:  # timestamps one period apart, however long the pause
                    t = last_t + period_ns
                if self.hw.drop_next > 0:
                    self.hw.drop_next -= 1
                    self.frames += 1
                    last_t = t
                    continue
                last_t = t
                if self.hw.budget is not None:
                    self.hw.budget -= 1
                while self._pending and self._pending[0][0] <= self.frames:
                    self._controls.update(self._pending.pop(0)[1])
                if not self._free:  # every buffer held by the application: frame lost
                    self.frames += 1
                    continue
                buf = self._free.pop()
                self.outstanding_peak = max(self.outstanding_peak,
                                            self.camera_config["buffer_count"] - len(self._free))  # type: ignore[index]
                y = ((np.arange(h)[:, None] * 3 + np.arange(w)[None, :] + self.frames * 7) % 251).astype(np.uint8)
                img = buf.reshape(h * 3 // 2, stride)
                img[:h, :w] = y
                img[:h, w:] = 0xAA  # padding
                img[h:] = 128
                md = {"SensorTimestamp": t, "FrameDuration": period_ns // 1000, **self._auto()}
                self.hw.produced[t] = y
                self.frames += 1
                self.completed_requests.append(CompletedRequest(self, buf, md))
                while len(self.completed_requests) > self._max_queue_len:
                    self.completed_requests.pop(0).release()
                finished = []
                while self._job_list and self._job_list[0].execute():
                    finished.append(self._job_list.pop(0))
            for job in finished:
                job.signal()

    # jobs
    def dispatch_functions(self, functions, wait, signal_function=None, immediate=False):
        if wait is None:
            wait = signal_function is None
        job = Job(functions, signal_function)
        with self._lock:
            self._job_list.append(job)
            done = []
            if self.completed_requests:
                while self._job_list and self._job_list[0].execute():
                    done.append(self._job_list.pop(0))
        for j in done:
            j.signal()
        return job.get_result() if wait else job

    def wait(self, job, timeout=None):
        return job.get_result(timeout=timeout)

    def cancel_all_and_flush(self) -> None:
        self.cancel_calls += 1
        with self._lock:
            for job in self._job_list:
                job.cancel()
            self._job_list = []

    def capture_request_(self):
        if not self.completed_requests:
            return (False, None)
        req = self.completed_requests.pop(0)
        self.handed_out.append(req)
        return (True, req)

    def capture_request(self, wait=None, signal_function=None, flush=None):
        return self.dispatch_functions([self.capture_request_], wait, signal_function)

    def capture_metadata_(self):
        if not self.completed_requests:
            return (False, None)
        req = self.completed_requests.pop(0)
        md = req.get_metadata()
        req.release()
        return (True, md)

    def capture_metadata(self, wait=None, signal_function=None):
        return self.dispatch_functions([self.capture_metadata_], wait, signal_function)
