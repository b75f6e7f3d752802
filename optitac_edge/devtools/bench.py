"""``optitac-edge bench``: how fast the per-frame loop is, measured, in one run.

Sections (all on the same frames, one process unless noted; see docs/performance.md):

``stages``
    The real :meth:`Pipeline.process` call timed per frame (``whole_frame``), and
    each stage re-run in isolation on that frame's state right after it
    (``gray``: gather of the fiber pixels, luma for RGB; ``fiber_means``: the
    segmented sum; ``baseline``: the signal against the baseline, gain
    compensation included; ``surface``; ``segment``: truncation and the
    multi-contact partition; ``moments``; ``hu`` (Hu and q4 of the binarised
    contact); ``shape``: the shape model; ``calibration``: centroid map and
    width model lookup; ``encode``: CONTACT message fill and wire encoding).
    Stages that do not run on a frame (no contact, model absent) are not
    sampled on it. Median, p99 and max, µs.
``reference``
    :class:`~optitac_edge.devtools.reference.ReferencePipeline` (the paper's method done
    the obvious way) on the first ``--reference-frames`` of the same frames, and
    the fast pipeline in paper mode on the same frames, :data:`FAST_PASSES`
    times over (a median of 300 samples of ~0.1 ms moved by 10 % between
    runs); ratios of medians.
``memory``
    tracemalloc: net bytes allocated per frame after warm-up (traced memory
    after minus before, divided by the frames) and the largest transient
    allocation within a frame; RSS growth over the ``stages`` pass.
``end_to_end``
    The service loop (:class:`~optitac_edge.service.loop.Service`) with the
    simulated camera paced at ``--fps`` writing serial frames into a pty; a
    separate process reads the pty and timestamps each CONTACT frame's last
    byte (CLOCK_MONOTONIC, shared by both processes): latency = that time
    minus the frame's timestamp in the packet. Frames dropped (camera
    sequence gaps), packets lost (sequence gaps seen by the reader plus
    frames the transport's queue dropped).
``startup``
    ``optitac-edge run --cal BUNDLE`` started as a new process, time from the
    spawn to the first packet read from the pty; and, separately, the time to
    import the runtime of a board with a real camera (service, pipeline, serial link, v4l2 camera;
    no simulator) and whether scipy / scikit-learn got imported.

Runtime code must not import this module (it imports the reference, which uses scipy).
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import threading
import time
import tracemalloc
import tty
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.pipeline import Pipeline, single_threaded_opencv

STAGES = ("whole_frame", "gray", "fiber_means", "baseline", "surface", "segment", "moments", "hu",
          "shape", "calibration", "encode")
#: Frames (after the baseline) the pipeline runs before anything is measured; at least every
#: distinct frame once, so that the allocator's high-water mark for the largest contact (OpenCV's
#: temporaries, ~1.5 MB of heap once) is reached before RSS growth is counted.
WARMUP_FRAMES = 200
#: Passes of the fast pipeline over the reference's frames (it takes ~1/40 of the time per frame).
FAST_PASSES = 10


def _warmup(frames: list[np.ndarray], rest: int) -> int:
    return max(WARMUP_FRAMES, len(frames) - rest)


def _summary(samples_ns: list[int] | np.ndarray) -> dict[str, Any]:
    a = np.asarray(samples_ns, dtype=np.float64) / 1e3
    if a.size == 0:
        return {"n": 0, "median_us": None, "p99_us": None, "max_us": None}
    return {"n": int(a.size), "median_us": round(float(np.median(a)), 2),
            "p99_us": round(float(np.percentile(a, 99)), 2), "max_us": round(float(a.max()), 2)}


def _rss_bytes() -> int:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):  # not Linux
        import resource

        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def machine() -> dict[str, Any]:
    """The machine the bench ran on."""
    cpu = platform.processor() or platform.machine()
    try:
        info = dict(line.split(":", 1) for line in Path("/proc/cpuinfo").read_text().splitlines()
                    if ":" in line)
        info = {k.strip().lower(): v.strip() for k, v in info.items()}
        cpu = info.get("model name") or info.get("hardware") or info.get("model") or cpu
    except OSError:
        pass
    import cv2

    return {"cpu": cpu, "cores": os.cpu_count(), "machine": platform.machine(),
            "python": platform.python_version(), "numpy": np.__version__, "opencv": cv2.__version__,
            "os": platform.platform(), "blas_threads_env": os.environ.get("OPENBLAS_NUM_THREADS"),
            "load_average_at_start": [round(v, 2) for v in os.getloadavg()]}


# -- inputs --------------------------------------------------------------------------------------


def sim_frames(n: int, rgb: bool, fps: float, rest: int, seed: int = 7) -> list[np.ndarray]:
    """``n`` frames of the live simulated camera (``rest`` contact-free, then random presses)."""
    from optitac_edge.sim.camera import SimCamera

    cam = SimCamera(fps=fps, rgb=rgb, seed=seed, rest_frames=rest, realtime=False)
    frames = []
    for _ in range(n):
        captured = cam.read()
        assert captured is not None
        frames.append(np.ascontiguousarray(captured.frame).copy())
    cam.close()
    return frames


def load_inputs(source: str, cal: Path | None, rgb: bool, workdir: Path, n_unique: int,
                fps: float) -> tuple[Any, Path, list[np.ndarray], str]:
    """(bundle, bundle path, frames, description)."""
    from optitac_edge.io.bundle_file import load_bundle, save_bundle

    if source == "sim":
        from optitac_edge.sim.bundles import cached_sim_bundle

        path = cal if cal is not None else cached_sim_bundle(workdir, rgb=rgb)
        bundle = load_bundle(path)
        rest = max(int(bundle.baseline_frames), 10)
        frames = sim_frames(n_unique, bundle.fibers.pixel_format == "rgb", fps, rest)
        return bundle, path, frames, f"simulated camera, {len(frames)} distinct frames"
    from optitac_edge.io.recording import Recording

    rec = Recording(source)
    frames = [np.ascontiguousarray(f) for f in rec]
    if cal is None:
        from optitac_edge.calibration.fibers import calibrate_fibers

        bundle = calibrate_fibers(rec.rest_frames(), rec.pixel_format)
        workdir.mkdir(parents=True, exist_ok=True)
        path = workdir / "cal-recording.npz"
        bundle = save_bundle(bundle, path)
    else:
        path = cal
        bundle = load_bundle(cal)
    return bundle, path, frames, f"recording {source}, {len(frames)} frames"


# -- in-process measurements -------------------------------------------------------------------


def _t(fn: Any, *args: Any) -> int:
    t0 = time.perf_counter_ns()
    fn(*args)
    return time.perf_counter_ns() - t0


class _Samples:
    """A preallocated int64 sample buffer with ``append``."""

    def __init__(self, n: int) -> None:
        self._a = np.empty(n, dtype=np.int64)
        self._a.fill(0)  # touch every page now: np.zeros' lazily mapped pages would grow the RSS
        self.n = 0

    def append(self, v: int) -> None:
        if self.n < self._a.size:
            self._a[self.n] = v
            self.n += 1

    @property
    def values(self) -> np.ndarray:
        return self._a[:self.n]


class StageTimer:
    """Times one pipeline's frames and re-runs each stage in isolation right after each frame,
    through the pipeline's parts' public methods."""

    def __init__(self, pipe: Pipeline, n: int) -> None:
        from optitac_edge.io.protocol.messages import ContactMessage
        from optitac_edge.io.protocol.wire import encode_contact

        self.pipe = pipe
        # preallocated, so that recording the samples does not grow the RSS being measured
        self.samples = {k: _Samples(n) for k in STAGES}
        self._surface = np.zeros(pipe.surface.size, dtype=np.float32)
        self._msg = ContactMessage()
        self._scratch = ContactEstimate()
        self._encode = encode_contact
        c = pipe.corrector
        self._shapes = c.shapes if c is not None else None
        self._centroid = c.centroid if c is not None else None
        self._width = c.width if c is not None else None

    def frame(self, frame: np.ndarray, t_ns: int) -> ContactEstimate:
        p = self.pipe
        s = self.samples
        t0 = time.perf_counter_ns()
        est = p.process(frame, t_ns)
        s["whole_frame"].append(time.perf_counter_ns() - t0)
        if not est.baseline_ready:
            return est
        s["gray"].append(_t(p.sampler.gather, frame))
        s["fiber_means"].append(_t(p.sampler.reduce, p.means))
        s["baseline"].append(_t(p.compute_signal, p.means, t_ns))
        s["surface"].append(_t(p.surface_op.compute, p.signal, self._surface))
        s["segment"].append(_t(self._segment))
        if est.contact:
            box = p.segmenter.box(p.surface)  # the pipeline's truncated surface (not timed)
            s["moments"].append(_t(p.blobs.ellipse, box.img, box.x, box.y, self._scratch))
            s["hu"].append(_t(self._hu, box.img, box.peak))
            if self._shapes is not None:
                s["shape"].append(_t(self._shapes.classify, est.features))
            if self._centroid is not None or self._width is not None:
                s["calibration"].append(_t(self._lookup, est))
        s["encode"].append(_t(self._encode_frame, est, t_ns))
        return est

    def _segment(self) -> None:
        """Truncation, the bounding box and (several contacts allowed) the partition."""
        p = self.pipe
        seg = p.segmenter
        cells = seg.truncate(self._surface)
        if cells:
            box = seg.box(self._surface)
            if p.options.max_contacts > 1:
                seg.partition(box, cells)

    def _hu(self, img: np.ndarray, peak: float) -> None:
        blobs = self.pipe.blobs
        blobs.shape_features(img, blobs.levels_of(peak)[1], self._scratch)

    def _lookup(self, est: ContactEstimate) -> None:
        if self._centroid is not None:
            self._centroid.correct(est.x_mm, est.y_mm)
        if self._width is not None:
            self._width.correct(est.major_mm, est.minor_mm)

    def _encode_frame(self, est: ContactEstimate, t_ns: int) -> None:
        self._msg.fill(est, t_ns, t_ns, True)
        self._encode(self._msg, 0)


def _feed(pipe: Any, frames: list[np.ndarray], rest: int, n: int, t_ns: int, period_ns: int,
          on_frame: Any = None) -> int:
    """Process ``n`` frames cycling over ``frames[rest:]`` (after the rest frames); returns the clock."""
    k = len(frames) - rest
    for i in range(n):
        frame = frames[rest + i % k]
        if on_frame is None:
            pipe.process(frame, t_ns)
        else:
            on_frame(frame, t_ns)
        t_ns += period_ns
    return t_ns


def measure_stages(bundle: Any, frames: list[np.ndarray], rest: int, n: int, fps: float) -> dict[str, Any]:
    """Whole-frame and per-stage times over ``n`` frames, RSS growth over them, contact share."""
    period = int(1e9 / fps)
    pipe = Pipeline(bundle)
    t = _feed(pipe, frames[:rest], 0, rest, 0, period) if rest else 0
    # warm-up with the stage re-runs too (their OpenCV temporaries reach their high-water mark)
    warm = _warmup(frames, rest)
    t = _feed(pipe, frames, rest, warm, t, period, StageTimer(pipe, warm).frame)
    timer = StageTimer(pipe, n)
    contacts = [0]

    def one(frame: np.ndarray, t_ns: int) -> None:
        contacts[0] += timer.frame(frame, t_ns).contact

    rss0 = _rss_bytes()
    _feed(pipe, frames, rest, n, t, period, one)
    rss1 = _rss_bytes()
    return {"frames": n, "contact_fraction": round(contacts[0] / max(n, 1), 3),
            "stages": {k: _summary(v.values) for k, v in timer.samples.items()},
            "rss_growth_bytes": rss1 - rss0, "rss_bytes": rss1,
            "surface": type(pipe.surface_op).__name__}


def measure_memory(bundle: Any, frames: list[np.ndarray], rest: int, n: int, fps: float) -> dict[str, Any]:
    """tracemalloc: net bytes per frame after warm-up, and the largest transient within a frame."""
    period = int(1e9 / fps)
    pipe = Pipeline(bundle)
    t = _feed(pipe, frames[:rest], 0, rest, 0, period) if rest else 0
    t = _feed(pipe, frames, rest, _warmup(frames, rest), t, period)
    tracemalloc.start()
    try:
        t = _feed(pipe, frames, rest, 50, t, period)  # tracemalloc's own first allocations
        transient = [0]

        def one(frame: np.ndarray, t_ns: int) -> None:
            tracemalloc.reset_peak()
            before = tracemalloc.get_traced_memory()[0]
            pipe.process(frame, t_ns)
            transient[0] = max(transient[0], tracemalloc.get_traced_memory()[1] - before)

        before = tracemalloc.get_traced_memory()[0]
        _feed(pipe, frames, rest, n, t, period, one)
        after = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    return {"frames": n, "net_bytes_per_frame": (after - before) / max(n, 1),
            "net_bytes_total": after - before, "max_transient_bytes_in_frame": transient[0]}


def measure_reference(bundle: Any, frames: list[np.ndarray], rest: int, n: int, fps: float,
                      fast_median_us: float | None) -> dict[str, Any]:
    """The paper's method done literally vs the fast pipeline in paper mode, same frames."""
    from optitac_edge.core.options import ContactOptions
    from optitac_edge.devtools.reference import ReferencePipeline

    period = int(1e9 / fps)
    ref = ReferencePipeline(bundle)
    fast = Pipeline(bundle, ContactOptions.paper())
    fast.set_corrector(None)
    t = 0
    for f in frames[:rest]:
        ref.process(f, t)
        fast.process(f, t)
        t += period
    k = len(frames) - rest
    ref_ns, fast_ns = [], []
    t_ref = t
    for i in range(n):  # the reference, then the fast pipeline: interleaved, the reference's
        ref_ns.append(_t(ref.process, frames[rest + i % k], t_ref))  # working set (tens of MB)
        t_ref += period  # would evict the fast one's tables from the caches every frame
    for i in range(n * FAST_PASSES):  # the same n frames, FAST_PASSES times
        fast_ns.append(_t(fast.process, frames[rest + i % n % k], t))
        t += period
    ref_s, fast_s = _summary(ref_ns), _summary(fast_ns)
    out = {"frames": n, "reference": ref_s, "fast_paper_mode": fast_s,
           "ratio_reference_to_fast_paper_mode": round(ref_s["median_us"] / fast_s["median_us"], 1)}
    if fast_median_us:
        out["ratio_reference_to_fast_all_options"] = round(ref_s["median_us"] / fast_median_us, 1)
    return out


# -- end to end and startup (pty + separate reader process) ------------------------------------


def _reader_main(fd: int, seconds: float, out_path: str, started_ns: int) -> None:
    """The separate process: read CONTACT frames from the pty, timestamp each at its last byte."""
    from optitac_edge.io.protocol.decoder import FrameDecoder
    from optitac_edge.io.protocol.wire import MsgType, decode_contact

    dec = FrameDecoder()
    rows: list[tuple[int, int, int, int]] = []  # (seq, t_us, received ns, age at fill µs)
    first_ns = None
    seqs: list[int] = []  # every frame's (CONTACT, STATUS) sequence number
    end = time.monotonic() + seconds
    os.set_blocking(fd, True)
    import select

    while time.monotonic() < end:
        r, _, _ = select.select([fd], [], [], 0.2)
        if not r:
            continue
        try:
            data = os.read(fd, 65536)
        except OSError:
            break
        now = time.monotonic_ns()
        for fr in dec.feed(data):
            seqs.append(fr.seq)
            if first_ns is None:
                first_ns = now
            if fr.type == MsgType.CONTACT:
                try:
                    age_us = decode_contact(fr.payload).age_us
                except ValueError:
                    age_us = -1
                rows.append((fr.seq, fr.t_us, now, age_us))
    Path(out_path).write_text(json.dumps({"rows": rows, "seqs": seqs, "first_ns": first_ns,
                                          "started_ns": started_ns,
                                          "decode_errors": dec.counters.__dict__}))


def _start_reader(master: int, seconds: float, out_path: str) -> subprocess.Popen:
    code = ("import sys; from optitac_edge.devtools.bench import _reader_main; "
            "_reader_main(int(sys.argv[1]), float(sys.argv[2]), sys.argv[3], int(sys.argv[4]))")
    return subprocess.Popen([sys.executable, "-c", code, str(master), str(seconds), out_path,
                             str(time.monotonic_ns())], pass_fds=(master,))


def _open_pty() -> tuple[int, int, str]:
    master, slave = os.openpty()
    tty.setraw(slave)  # no newline translation: the link is binary
    return master, slave, os.ttyname(slave)


def _latencies(rows: list[list[int]], seqs: list[int]) -> tuple[np.ndarray, int]:
    """Latency (ns) of each CONTACT packet, and the frames missing from the sequence numbers."""
    lat = []
    for _seq, t_us, recv_ns, _age in rows:
        recv_us = recv_ns // 1000
        age_us = (recv_us - t_us) % (1 << 32)  # t_us wraps at 32 bits
        lat.append(age_us * 1000 + recv_ns % 1000)
    gaps = np.mod(np.diff(np.asarray(seqs, dtype=np.int64)), 1 << 16)
    missing = int(np.sum(gaps[gaps > 1] - 1)) if gaps.size else 0
    return np.asarray(lat, dtype=np.float64), missing


def _dropped_in_stall(now_ns: int, due_ns: int, dropped_published_ns: int, period_ns: float) -> bool:
    """Whether a frame pushed out of the replay camera's queue at ``now_ns`` was lost to a process stall.

    Yes when the frame pushing it out is published a period or more after it was due
    (nothing in the process ran, the capture thread included), or when the dropped
    frame itself had waited less than half a period: it came in the burst of late
    frames the capture thread publishes right after such a stall, and the loop, back
    from the same stall, had no time to take it. Otherwise the capture thread was on
    time and the frame waited its ``queue_frames`` periods: the loop's own drop.
    """
    return now_ns - due_ns >= period_ns or now_ns - dropped_published_ns < period_ns / 2


def _replay_camera(frames: list[np.ndarray], rest: int, fps: float, pixel_format: str,
                   queue_frames: int) -> Any:
    """A camera delivering pre-rendered frames at ``fps`` from a capture thread (see PacedReplayCamera)."""
    from optitac_edge.errors import CameraError
    from optitac_edge.io.cameras.base import Camera, CapturedFrame

    class PacedReplayCamera(Camera):
        """Frames (rest first, then the rest cycled) published at ``k / fps`` by a capture thread.

        The thread queues each frame, stamped when published, as the hardware
        backends' frame ring does: up to ``queue_frames`` wait, and when one more
        comes the oldest is dropped (a gap in ``seq``, counted as dropped). Like a
        camera whose driver delivers by DMA: the source costs the loop nothing, so
        the loop itself is measured.
        """

        def __init__(self) -> None:
            super().__init__()
            h, w = frames[0].shape[:2]
            self.pixel_format, self.fps = pixel_format, fps
            self.height, self.width = (h * 2 // 3, w) if pixel_format == "yuv420" else (h, w)
            self._waiting: deque[CapturedFrame] = deque()
            #: (seq, stalled) of each frame dropped from the queue (the loop had not taken it when
            #: ``queue_frames`` newer ones came), see :func:`_dropped_in_stall`
            self.overwritten: list[tuple[int, bool]] = []
            #: (seq, ns late) of each frame the capture thread published a period or more late
            self.stalls: list[tuple[int, int]] = []
            self._cond = threading.Condition()
            self._stop = threading.Event()
            self._thread = threading.Thread(target=self._capture, name="bench-capture", daemon=True)
            self._thread.start()

        def _capture(self) -> None:
            period = 1e9 / fps
            t0 = time.monotonic_ns()
            k, seq = len(frames) - rest, 0
            while not self._stop.is_set():
                due = t0 + int(seq * period)
                now = time.monotonic_ns()
                if due > now:
                    time.sleep((due - now) / 1e9)
                i = seq if seq < len(frames) else rest + (seq - rest) % k
                with self._cond:
                    now = time.monotonic_ns()
                    if now - due >= period:
                        self.stalls.append((seq + 1, now - due))
                    if len(self._waiting) == queue_frames:
                        old = self._waiting.popleft()
                        self.overwritten.append((old.seq, _dropped_in_stall(now, due, old.t_ns, period)))
                    self._waiting.append(CapturedFrame(frames[i], now, seq + 1))
                    self._cond.notify_all()
                seq += 1

        def _read_internal(self, timeout_s: float) -> CapturedFrame:
            deadline = time.monotonic() + timeout_s
            with self._cond:
                while not self._waiting:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        raise CameraError("replay camera: no frame in time")
                    self._cond.wait(left)
                return self._waiting.popleft()

        def _close_internal(self) -> None:
            self._stop.set()
            self._thread.join(timeout=1.0)

    return PacedReplayCamera()


def _steal_jiffies() -> int:
    """CPU time the hypervisor gave to others while this VM wanted it (/proc/stat), jiffies."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
        return int(fields[8]) if fields[0] == "cpu" and len(fields) > 8 else 0
    except (OSError, ValueError):
        return 0


def _drop_causes(camera: Any, fps: float, steal_jiffies: int) -> dict[str, Any]:
    """Why frames were dropped: the loop too slow with the camera on time, or whole-process stalls.

    Only frames between the first and the last one the loop read count: the capture
    thread publishes from its start (while the service is still being built) until
    the camera is closed after the run.
    """
    if not hasattr(camera, "overwritten") or camera._last_seq is None:  # live sim camera: not classified
        return {}
    last = camera._last_seq
    first = last - (camera.frames_read + camera.frames_dropped) + 1
    lost = [stalled for seq, stalled in list(camera.overwritten) if first < seq < last]
    stalls = np.asarray([ns for seq, ns in list(camera.stalls) if first < seq <= last], dtype=np.float64) / 1e6
    return {"frames_dropped_by_pipeline": lost.count(False),
            "frames_dropped_in_process_stalls": lost.count(True),
            "process_stalls": {"count": int(stalls.size),
                               "max_ms": round(float(stalls.max()), 2) if stalls.size else 0.0,
                               "threshold_ms": round(1e3 / fps, 2)},
            "cpu_steal_ms": steal_jiffies * 1000 // os.sysconf("SC_CLK_TCK")}


def measure_end_to_end(cal: Path, fps: float, seconds: float, rgb: bool,
                       frames: list[np.ndarray] | None = None, rest: int = 10,
                       queue_frames: int | None = None) -> dict[str, Any]:
    """The service loop paced at ``fps`` into a pty, read by a separate process.

    With ``frames``, the camera replays them (pre-rendered, see ``_replay_camera``);
    otherwise it is the live simulated camera (rendering ~1 ms a frame in its own thread).
    ``queue_frames`` overrides the sim board's ``camera.queue_frames``.
    """
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.transports.serial import SerialTransport
    from optitac_edge.service.board_config import load_board_config
    from optitac_edge.service.loop import Service
    from optitac_edge.sim.camera import SimCamera

    master, slave, path = _open_pty()
    out = Path(tempfile.mkdtemp(prefix="optitac-bench-")) / "e2e.json"
    bundle = load_bundle(cal)
    overrides: dict[str, Any] = {"camera.fps": fps, "link.transport": "serial", "link.serial_url": path}
    if queue_frames is not None:
        overrides["camera.queue_frames"] = queue_frames
    config = load_board_config("sim", env={}, overrides=overrides)
    reader = _start_reader(master, seconds + 3.0, str(out))
    time.sleep(0.5)  # reader up
    if frames is not None:
        camera = _replay_camera(frames, rest, fps, bundle.fibers.pixel_format, config.camera.queue_frames)
    else:
        camera = SimCamera(fps=fps, rgb=bundle.fibers.pixel_format == "rgb", rest_frames=rest, seed=11,
                           queue_frames=config.camera.queue_frames)
    transport = SerialTransport(path, baudrate=921600, sensor_id=config.sensor.id)
    steal0 = _steal_jiffies()
    try:
        service = Service(config, bundle, camera, transport)
        stop = threading.Event()
        stats = service.run(stop, duration_s=seconds)
        steal = _steal_jiffies() - steal0
        transport.wait_idle(1.0)
        t_stats = dict(transport.stats())
    finally:
        transport.close()
        camera.close()
        time.sleep(0.2)  # the reader drains the pty
        os.close(slave)  # no slave left open: the reader's next read fails and it ends
    reader.wait(timeout=seconds + 30)
    os.close(master)
    data = json.loads(out.read_text())
    lat, missing = _latencies(data["rows"], data["seqs"])
    s = _summary(lat)
    a = _summary([r[3] * 1000 for r in data["rows"] if r[3] >= 0])
    return {"camera": "replayed pre-rendered frames" if frames is not None else "live simulated camera",
            "fps": fps, "seconds": seconds, "queue_frames": config.camera.queue_frames,
            "frames": stats.frames, "sent": stats.sent,
            "received": len(data["rows"]), "frames_dropped": stats.frames_dropped,  # sequence gaps read
            # written but not read (sequence gaps and a missing tail), plus never written
            "packets_lost": (max(t_stats.get("sent", 0) - len(data["seqs"]), missing)
                             + t_stats.get("dropped", 0) + t_stats.get("dropped_disconnected", 0)
                             + t_stats.get("send_errors", 0)),
            "sequence_gaps": missing,
            **_drop_causes(camera, fps, steal),
            "achieved_fps": round(stats.frames / seconds, 1),
            "latency_us": {"p50": s["median_us"], "p99": s["p99_us"], "max": s["max_us"]},
            # the part before the message was filled (camera delivery + processing), from its age field
            "frame_to_fill_us": {"p50": a["median_us"], "p99": a["p99_us"], "max": a["max_us"]},
            "transport": {k: v for k, v in t_stats.items() if isinstance(v, (int, float, str, bool))}}


def measure_startup(cal: Path, fps: float) -> dict[str, Any]:
    """Process start to first packet (``optitac-edge run --cal``), and the runtime's import time."""
    master, slave, path = _open_pty()
    out = Path(tempfile.mkdtemp(prefix="optitac-bench-")) / "startup.json"
    reader = _start_reader(master, 30.0, str(out))
    time.sleep(0.5)
    code = "import sys; from optitac_edge.cli import main; raise SystemExit(main())"
    t0 = time.monotonic_ns()
    proc = subprocess.Popen([sys.executable, "-c", code, "run", "--cal", str(cal), "--serial", path,
                             "--fps", str(fps), "--duration", "2"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    proc.wait(timeout=60)
    time.sleep(0.2)
    os.close(slave)
    reader.wait(timeout=30)
    os.close(master)
    data = json.loads(out.read_text())
    first = data["first_ns"]
    probe = ("import time, sys; t0 = time.perf_counter(); "
             "import optitac_edge.service.loop, optitac_edge.service.wiring, optitac_edge.core.pipeline, "
             "optitac_edge.io.transports.serial, optitac_edge.io.cameras.v4l2; t1 = time.perf_counter(); "
             "from optitac_edge.io.bundle_file import load_bundle; from optitac_edge.core.pipeline import Pipeline; "
             "p = Pipeline(load_bundle(sys.argv[1])); t2 = time.perf_counter(); "
             "heavy = sorted(m for m in ('scipy', 'sklearn', 'matplotlib', 'onnxruntime', 'pandas') "
             "if m in sys.modules); "
             "print(t1 - t0, t2 - t1, ','.join(heavy))")
    res = subprocess.run([sys.executable, "-c", probe, str(cal)], capture_output=True, text=True, timeout=60, check=False)
    parts = res.stdout.split()
    return {"start_to_first_packet_s": None if first is None else round((first - t0) / 1e9, 3),
            "exit_code": proc.returncode,
            "import_runtime_s": round(float(parts[0]), 3) if parts else None,
            "load_bundle_and_build_pipeline_s": round(float(parts[1]), 3) if len(parts) > 1 else None,
            "heavy_modules_imported": (parts[2].split(",") if len(parts) > 2 else [])}


# -- the command ---------------------------------------------------------------------------------


def run_bench(frames: int = 20000, source: str = "sim", fps: float = 240.0, cal: Path | None = None,
              rgb: bool = False, workdir: Path | None = None, reference_frames: int = 300,
              memory_frames: int = 2000, e2e_seconds: float = 60.0, startup: bool = True,
              unique_frames: int = 600, queue_frames: int | None = None,
              log: Any = print) -> dict[str, Any]:
    """Run every section; returns the results (see the module docstring)."""
    workdir = workdir or Path(tempfile.gettempdir()) / "optitac-bench"
    t_start = time.time()
    bundle, cal_path, frame_list, described = load_inputs(source, cal, rgb, workdir, unique_frames, fps)
    rest = int(bundle.baseline_frames) if source != "sim" else max(int(bundle.baseline_frames), 10)
    rest = min(rest, len(frame_list) - 1)
    fmt = bundle.fibers.pixel_format
    h, w = bundle.fibers.height, bundle.fibers.width
    res: dict[str, Any] = {"machine": machine(), "source": described, "pixel_format": fmt,
                           "frame_size": [w, h], "bundle": str(cal_path),
                           "options": {k: getattr(bundle.options, k) for k in
                                       ("relative", "compensate_gain", "fill_dead", "max_contacts",
                                        "track_baseline", "peak_fraction", "shape_fraction")},
                           "models": sorted(k for k in ("centroid", "width", "shapes")
                                            if k in bundle.extra_meta),
                           "fibers": bundle.fibers.n_fibers, "fiber_pixels": int(bundle.fibers.pixel_index.size),
                           "mesh": bundle.grid.n}
    log(f"bench: {described}; {fmt} {w}x{h}; {frames} frames")
    with single_threaded_opencv():  # as the service runs the loop
        res["pipeline"] = measure_stages(bundle, frame_list, rest, frames, fps)
        whole = res["pipeline"]["stages"]["whole_frame"]
        log(f"  whole frame: median {whole['median_us']} µs, p99 {whole['p99_us']} µs, max {whole['max_us']} µs")
        if reference_frames > 0:
            res["reference"] = measure_reference(bundle, frame_list, rest, reference_frames, fps,
                                                 whole["median_us"])
            r = res["reference"]
            fast = r["fast_paper_mode"]
            log(f"  reference: median {r['reference']['median_us']} µs ({r['reference']['n']} frames); "
                f"paper mode: median {fast['median_us']} µs ({fast['n']} frames); "
                f"x{r['ratio_reference_to_fast_paper_mode']}")
        if memory_frames > 0:
            res["memory"] = measure_memory(bundle, frame_list, rest, memory_frames, fps)
            res["memory"]["rss_growth_bytes"] = res["pipeline"]["rss_growth_bytes"]
            res["memory"]["rss_frames"] = frames
            log(f"  memory: {res['memory']['net_bytes_per_frame']:.1f} net bytes/frame, "
                f"RSS +{res['memory']['rss_growth_bytes']} B over {frames} frames")
    if e2e_seconds > 0:
        if source != "sim":
            res["end_to_end"] = {"skipped": "needs --source sim"}
        else:
            res["end_to_end"] = e = measure_end_to_end(cal_path, fps, e2e_seconds, rgb, frame_list, rest,
                                                                queue_frames)
            why = ""
            if "frames_dropped_by_pipeline" in e:
                st = e["process_stalls"]
                why = (f" (by the pipeline {e['frames_dropped_by_pipeline']}, in process stalls "
                       f"{e['frames_dropped_in_process_stalls']}: {st['count']} stalls >= {st['threshold_ms']} ms, "
                       f"max {st['max_ms']} ms; CPU steal {e['cpu_steal_ms']} ms)")
            log(f"  end to end @ {fps} fps, {e2e_seconds} s, queue {e['queue_frames']}: {e['frames']} frames, dropped "
                f"{e['frames_dropped']}{why}, lost {e['packets_lost']}, latency p50/p99/max "
                f"{e['latency_us']['p50']}/{e['latency_us']['p99']}/{e['latency_us']['max']} µs")
    if startup:
        if source != "sim" or fmt != "gray":
            res["startup"] = {"skipped": "needs --source sim and gray frames (the sim board's camera)"}
        else:
            res["startup"] = s = measure_startup(cal_path, fps)
            log(f"  startup: first packet after {s['start_to_first_packet_s']} s "
                f"(runtime import {s['import_runtime_s']} s; heavy modules: "
                f"{s['heavy_modules_imported'] or 'none'})")
    res["elapsed_s"] = round(time.time() - t_start, 1)
    res["machine"]["load_average_at_end"] = [round(v, 2) for v in os.getloadavg()]
    return res


def format_table(res: dict[str, Any]) -> str:
    """The stage table as Markdown."""
    lines = ["| stage | median µs | p99 µs | max µs | frames |", "|---|---:|---:|---:|---:|"]
    for k, v in res["pipeline"]["stages"].items():
        lines.append(f"| {k} | {v['median_us']} | {v['p99_us']} | {v['max_us']} | {v['n']} |")
    return "\n".join(lines)

