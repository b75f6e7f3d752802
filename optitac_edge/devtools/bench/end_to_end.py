"""End to end: the service loop paced at the camera's rate into a pty; start-up to the first packet."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from optitac_edge.devtools.bench.link import latencies, open_pty, start_reader
from optitac_edge.devtools.bench.replay_camera import drop_causes, paced_replay_camera, steal_jiffies
from optitac_edge.devtools.bench.samples import summary

if TYPE_CHECKING:
    from optitac_edge.config import SensorConfig
    from optitac_edge.core.bundle import CalibrationBundle
    from optitac_edge.core.frame_result import FrameResult
    from optitac_edge.devtools.bench.network import BenchNetwork
    from optitac_edge.io.cameras.base import Camera
    from optitac_edge.service.loop import Service, ServiceStats
    from optitac_edge.service.view.live import LiveView
    from optitac_edge.service.view.server import ViewServer


@dataclass(frozen=True)
class EndToEnd:
    """One end-to-end run: the service loop paced at ``fps`` for ``seconds`` into a pty.

    With ``frames``, the camera replays them (pre-rendered, see ``paced_replay_camera``; the first
    ``rest`` contact-free); otherwise it is the live simulated camera (rendering ~1 ms a frame in its
    own thread). ``queue_frames`` overrides the sim board's ``camera.queue_frames``. With ``view``
    (``HOST:PORT``) the live view is served during the run (``on_view`` gets its URL), so the cost of
    a browser on it is in the figures. With ``bundles`` (instead of ``cal``) the camera reads one
    sensor per bundle (patches of one frame, ids 1, 2, ...), as a board with several sensors on one
    camera runs. With ``publish`` every sensor's contacts, status and signal also go on Zenoh to a
    subscriber process and into an MCAP file (:mod:`optitac_edge.devtools.bench.network`). ``workers``:
    the service's sensor worker threads (None: as the service chooses from the cores).
    """

    cal: Path | None
    fps: float
    seconds: float
    rgb: bool = False
    frames: list[np.ndarray] | None = None
    rest: int = 10
    queue_frames: int | None = None
    view: str | None = None
    on_view: Callable[[str], object] | None = None
    bundles: list[CalibrationBundle] | None = None
    publish: bool = False
    workers: int | None = None


def measure_end_to_end(run: EndToEnd) -> dict[str, Any]:
    """The service loop of ``run``, its packets read from the pty by a separate process."""
    with tempfile.TemporaryDirectory(prefix="optitac-bench-") as tmp:
        return _end_to_end(Path(tmp) / "e2e.json", run)


def _end_to_end(out: Path, run: EndToEnd) -> dict[str, Any]:
    """:func:`measure_end_to_end`, the reader writing its figures to ``out``."""
    from optitac_edge.config import SensorConfig, load_board_config
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.transports.serial import SerialTransport
    from optitac_edge.service.loop import Service

    fps, seconds = run.fps, run.seconds
    master, slave, path = open_pty()
    bundles = run.bundles
    if bundles is None:
        assert run.cal is not None, "measure_end_to_end needs cal or bundles"
        bundles = [load_bundle(run.cal)]
    bundle = bundles[0]
    overrides: dict[str, Any] = {"camera.fps": fps, "link.transport": "serial", "link.serial_url": path}
    if run.queue_frames is not None:
        overrides["camera.queue_frames"] = run.queue_frames
    config = load_board_config("sim", env={}, overrides=overrides)
    reader = start_reader(master, seconds + 3.0, str(out))
    time.sleep(0.5)  # reader up
    camera = _camera(run, bundle.fibers.pixel_format, config.camera.queue_frames)
    transport = SerialTransport(path, baudrate=921600)
    steal0 = steal_jiffies()
    outputs = _Outputs()
    try:
        sensors = [(SensorConfig(id=k + 1, name=f"patch{k + 1}"), b) for k, b in enumerate(bundles)]
        service = Service(config, bundle, camera, transport, sensors=sensors if len(bundles) > 1 else None,
                          workers=run.workers)
        workers = service.pool.workers
        outputs.attach(service, run, sensors if len(bundles) > 1 else [(config.sensor, bundle)])
        stop = threading.Event()
        cpu = MainThreadCpu(warm_frames=int(fps * min(1.0, seconds / 4)))  # from the second second on (short runs: the first quarter)
        stats = service.run(stop, duration_s=seconds, on_result=cpu.on_result)
        cpu.stop(stats.frames)
        steal = steal_jiffies() - steal0
        transport.wait_idle(1.0)
        t_stats = dict(transport.stats())
    finally:
        outputs.close()
        transport.close()
        camera.close()
        time.sleep(0.2)  # the reader drains the pty
        os.close(slave)  # no slave left open: the reader's next read fails and it ends
    reader.wait(timeout=seconds + 30)
    os.close(master)
    data = json.loads(out.read_text())
    lat, missing = latencies(data["rows"], data["seqs"])
    s = summary(lat)
    a = summary([r[3] * 1000 for r in data["rows"] if r[3] >= 0])
    return {"camera": "replayed pre-rendered frames" if run.frames is not None else "live simulated camera",
            "fps": fps, "seconds": seconds, "queue_frames": config.camera.queue_frames,
            "frames": stats.frames, "sent": stats.sent,
            "received": len(data["rows"]), "frames_dropped": stats.frames_dropped,  # sequence gaps read
            # written but not read (sequence gaps and a missing tail), plus never written
            "packets_lost": (max(t_stats.get("sent", 0) - len(data["seqs"]), missing)
                             + t_stats.get("dropped", 0) + t_stats.get("dropped_disconnected", 0)
                             + t_stats.get("send_errors", 0)),
            "sequence_gaps": missing,
            **drop_causes(camera, fps, steal),
            "achieved_fps": round(stats.frames / seconds, 1), "sensor_workers": workers,
            **cpu.result(),
            "latency_us": {"p50": s["median_us"], "p99": s["p99_us"], "max": s["max_us"]},
            # the part before the message was filled (camera delivery + processing), from its age field
            "frame_to_fill_us": {"p50": a["median_us"], "p99": a["p99_us"], "max": a["max_us"]},
            "transport": {k: v for k, v in t_stats.items() if isinstance(v, (int, float, str, bool))},
            **({"view": outputs.view_stats} if run.view is not None else {}),
            **({"publish": outputs.net_stats} if run.publish else {})}


def _camera(run: EndToEnd, pixel_format: str, queue_frames: int) -> Camera:
    """The run's camera: its frames replayed at its rate, or the live simulated camera."""
    if run.frames is not None:
        return paced_replay_camera(run.frames, run.rest, run.fps, pixel_format, queue_frames)
    from optitac_edge.sim.camera import SimCamera

    return SimCamera(fps=run.fps, rgb=pixel_format == "rgb", rest_frames=run.rest, seed=11, queue_frames=queue_frames)


class _Outputs:
    """The run's network publisher and live view (either may be off), and what they counted once closed."""

    def __init__(self) -> None:
        self.net: BenchNetwork | None = None
        self.live: LiveView | None = None
        self.server: ViewServer | None = None
        self.net_stats: dict[str, Any] = {}
        self.view_stats: dict[str, Any] = {}

    def attach(self, service: Service, run: EndToEnd, named: list[tuple[SensorConfig, CalibrationBundle]]) -> None:
        if run.publish:
            from optitac_edge.devtools.bench.network import BenchNetwork
            from optitac_edge.service.session import network_sensor

            self.net = BenchNetwork([network_sensor(s, b) for s, b in named])
            service.network = self.net.output
        if run.view is not None:
            from optitac_edge.service.view.live import LiveView
            from optitac_edge.service.view.server import ViewServer

            bundle = named[0][1]
            self.live = LiveView(bundle, bundle.fibers.pixel_format)
            self.server = ViewServer(self.live, run.view)
            service.view = self.live
            if run.on_view is not None:
                run.on_view(self.server.url)

    def close(self) -> None:
        if self.net is not None:
            self.net_stats = self.net.close()
        if self.server is not None and self.live is not None:
            live = self.live
            self.view_stats = {"updates": live.published.seq if live.published else 0, "skipped": live.skipped,
                               "bad_requests": self.server.bad_requests}
            self.server.close()
            live.close()


class MainThreadCpu:
    """The service thread's CPU time and context switches per frame, from frame ``warm_frames`` to the end.

    Everything the loop does counts: waiting for and taking the camera's frame,
    the frame check, the pipeline, the message fill and encode, the transport's
    hand-off, commands and STATUS (``getrusage(RUSAGE_THREAD)``: user + system).
    """

    def __init__(self, warm_frames: int) -> None:
        self.warm = max(int(warm_frames), 1)
        self._start: tuple[float, int, int, int] | None = None
        self._end: tuple[float, int, int, int] | None = None

    @staticmethod
    def _sample(frames: int) -> tuple[float, int, int, int]:
        r = resource.getrusage(resource.RUSAGE_THREAD)
        return r.ru_utime + r.ru_stime, r.ru_nvcsw, r.ru_nivcsw, frames

    def on_result(self, _result: FrameResult, stats: ServiceStats) -> None:
        if self._start is None and stats.frames >= self.warm:
            self._start = self._sample(stats.frames)

    def stop(self, frames: int) -> None:
        """Call on the service's thread right after ``Service.run`` returned."""
        self._end = self._sample(frames)

    def result(self) -> dict[str, Any]:
        if self._start is None or self._end is None or self._end[3] <= self._start[3]:
            return {"main_thread": None}
        n = self._end[3] - self._start[3]
        return {"main_thread": {
            "frames": n, "cpu_us_per_frame": round((self._end[0] - self._start[0]) / n * 1e6, 1),
            "voluntary_switches_per_frame": round((self._end[1] - self._start[1]) / n, 2),
            "involuntary_switches_per_frame": round((self._end[2] - self._start[2]) / n, 3)}}


def measure_startup(cal: Path, fps: float) -> dict[str, Any]:
    """Process start to first packet (``optitac-edge run --cal``), and the runtime's import time."""
    with tempfile.TemporaryDirectory(prefix="optitac-bench-") as tmp:
        return _startup(Path(tmp) / "startup.json", cal, fps)


def _startup(out: Path, cal: Path, fps: float) -> dict[str, Any]:
    master, slave, path = open_pty()
    reader = start_reader(master, 30.0, str(out))
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
