"""``optitac-edge run``: the service (capture, process, send), its status line and its summary."""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Any

from optitac_edge.cli.common import COUNT, EXIT_INTERRUPTED, FPS, add_board, board_config, number
from optitac_edge.errors import OptiTacError
from optitac_edge.io.files import AtomicFile
from optitac_edge.io.logs import LIVE_LINE, NonBlockingLogging
from optitac_edge.io.startup import STARTUP

if TYPE_CHECKING:
    from typing_extensions import Self

    from optitac_edge.cli.common import Subcommands
    from optitac_edge.config import BoardConfig
    from optitac_edge.core.contact import ContactEstimate
    from optitac_edge.core.frame_result import FrameResult
    from optitac_edge.io.transports.base import Transport
    from optitac_edge.service.loop import Service
    from optitac_edge.service.session import BoardSession
    from optitac_edge.service.stats import ServiceStats


def add_parser(sub: Subcommands) -> None:
    """``run [--board B] [--serial PORT | --can CHANNEL] ...``."""
    p = sub.add_parser("run", help="capture -> process -> transmit (default: the built-in simulated sensor)")
    add_board(p)
    p.add_argument("--cal", type=Path, default=None, help="use this bundle (default: the board's)")
    p.add_argument("--serial", default=None, metavar="PORT", help="serial device or pyserial URL (overrides the board)")
    p.add_argument("--can", default=None, metavar="CHANNEL", help="CAN channel (overrides the board)")
    p.add_argument("--duration", type=number(0, 1e8, lo_open=True), default=None, metavar="S",
                   help="stop cleanly after S seconds")
    p.add_argument("--frames", type=COUNT, default=None, help="stop after N frames")
    p.add_argument("--fps", type=FPS, default=None, help="camera frame rate (overrides the board)")
    p.add_argument("--view", default=None, metavar="HOST:PORT",
                   help="serve the live view here (off by default; e.g. 127.0.0.1:8080, see docs/bring-up.md)")
    p.add_argument("--publish", default=None, metavar="zenoh[:CONFIG]",
                   help="publish every sensor's contacts and status on Zenoh as ROS 2 topics (rmw_zenoh), with "
                        "this Zenoh JSON5 config if given; 'none' turns the board's [publish.zenoh] off "
                        "(docs/network.md)")
    p.add_argument("--mcap", default=None, metavar="FILE",
                   help="also write every sensor's contacts and status to this MCAP file (rotation: [publish.mcap] "
                        "max_mb, max_minutes)")
    p.add_argument("--stage-times", type=Path, default=None, metavar="FILE",
                   help="at exit, write the frame loop's CPU per frame by stage (pipeline, send path) to this "
                        "JSON file (docs/performance.md)")
    p.add_argument("--foxglove", default=None, metavar="HOST:PORT",
                   help="serve contacts, status, each sensor's image, surface and overlay live to Foxglove or "
                        "Lichtblick (e.g. 127.0.0.1:8765; needs the foxglove extra)")


def _status_line(est: ContactEstimate | None, fps: float | None) -> str:
    """The line of one sensor (``est`` None: its baseline is not ready)."""
    rate = "  -.- fps" if fps is None else f"{fps:5.1f} fps"
    if est is None:
        return f"{rate}  baselining..."
    if not est.contact:
        return f"{rate}  no contact"
    shape = f" {est.shape}" if est.shape else ""
    depth = f" depth {est.depth_mm:.2f} mm" if math.isfinite(est.depth_mm) else ""
    # what matters first comes first: the line is cut at the terminal's width
    return (f"{rate}  CONTACT {est.x_mm:+.2f},{est.y_mm:+.2f} mm {est.major_mm:.1f}x{est.minor_mm:.1f} mm "
            f"{est.angle_deg:+.0f}°{shape} strength {est.strength:.0f}{depth}")


def _brief(name: str, est: ContactEstimate | None) -> str:
    """One sensor of several, in a few words (``est`` None: its baseline is not ready)."""
    if est is None:
        return f"{name}: baselining"
    if not est.contact:
        return f"{name}: -"
    return f"{name}: {est.x_mm:+.1f},{est.y_mm:+.1f} mm strength {est.strength:.0f}"


def _fps_overrides(args: argparse.Namespace) -> dict[str, float]:
    """``run --fps``: the frame rate of every camera of the board."""
    if args.fps is None:
        return {}
    from optitac_edge.config import load_board_config

    named = load_board_config(args.board, env=os.environ).named_cameras
    return {f"cameras.{name}.fps": args.fps for name in named} or {"camera.fps": args.fps}


def _publish_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """``--publish zenoh[:CONFIG]`` (or ``none``: the board's Zenoh off), ``--mcap FILE`` and ``--foxglove
    HOST:PORT`` as board config overrides of its ``[publish.NAME]``."""
    out: dict[str, Any] = {}
    value = getattr(args, "publish", None)
    if value is not None:
        backend, _, path = value.partition(":")
        if backend not in ("zenoh", "none") or (backend == "none" and path):
            raise OptiTacError(f"--publish must be zenoh, zenoh:CONFIG or none, got {value!r}")
        if backend == "none":
            out.update({"publish.zenoh": False, "publish.virtual": False})
        else:
            out.update({"publish.zenoh": True, **({"publish.zenoh.config": path} if path else {})})
    if getattr(args, "mcap", None):
        out["publish.mcap.path"] = args.mcap
    if getattr(args, "foxglove", None):
        out["publish.foxglove.bind"] = args.foxglove
    return out


def _say_summary(service: Service, several_cameras: bool, several_sensors: bool, say: Callable[..., None]) -> None:
    """A camera's frames, drops and errors at the end of a run; each sensor's, and why one sent no contact."""
    stats = service.stats
    commands = " ".join(f"{k}={v}" for k, v in sorted(stats.commands.items())) or "none"
    # with several sensors on a camera, the contacts are each sensor's (below): a camera's frame is one
    contacts = f", {stats.contacts} with contact" if len(service.channels) == 1 else ""
    before = stats.frames_dropped_before_loop
    say("%sprocessed %d frames%s, dropped %d%s, camera errors %d, processing errors %d, commands %s",
        f"camera {service.camera_name}: " if several_cameras else "", stats.frames, contacts, stats.frames_dropped,
        f" (and {before} before it caught up with the camera, which streamed while the bundles were made)" if before else "",
        stats.camera_errors, stats.processing_errors, commands)
    for ch in service.channels:
        if several_sensors:
            say("  sensor %d %r: %d frames, %d with contact", ch.sensor_id, ch.name, ch.frames, ch.contacts)
        if ch.mismatch is not None:
            say("  sensor %d %r: no contact sent: %s", ch.sensor_id, ch.name, ch.mismatch)


def run(args: argparse.Namespace) -> int:
    STARTUP.mark("imports")
    if args.duration is not None and not args.duration > 0:
        raise OptiTacError("--duration must be positive")
    link = {}
    if args.serial is not None:
        link = {"link.transport": "serial", "link.serial_url": args.serial}
    elif args.can is not None:
        link = {"link.transport": "can", "link.can_channel": args.can}
    config = board_config(args, **link, **_fps_overrides(args), **_publish_overrides(args))
    STARTUP.mark("board config")
    stop = threading.Event()
    received: list[int] = []

    def on_signal(signum: int, frame: object) -> None:  # Ctrl-C, systemd's stop, a closed terminal
        received.append(signum)
        stop.set()

    previous = {signum: signal.signal(signum, on_signal) for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)}
    # run's own lines go to stdout through a queue too: a stdout nobody reads never holds up the service
    console = NonBlockingLogging(logging.INFO, sys.stdout, logger="optitac_edge.console", fmt="%(message)s",
                                 always=True).start()
    services: list[Service] = []
    try:
        say = logging.getLogger("optitac_edge.console").info
        services = _run_service(args, config, stop, say)
        for service in services:
            _say_summary(service, len(services) > 1, len(config.sensors) > 1, say)
        if services:
            say("%s", _link_summary(services[0].transport))
            network = service.network
            if network is not None:
                # "published": taken by the publisher; a recording's failed writes are said of the run as a whole
                lost = network.publisher.undelivered
                taken = "published" if not lost else "given to the publisher"
                for ch in service.channels:
                    published, dropped = network.counters(ch.sensor_id)
                    say("  sensor %d %r: %d messages %s, %d dropped (publishing errors %d; %s)",
                        ch.sensor_id, ch.name, published, taken, dropped, network.errors, network.publisher.where)
                if lost:
                    say("  %d of the messages NOT written (failed writes; what was written is below)", lost)

        network = services[0].network if services else None
        for line in network.publisher.summary if network is not None else ():
            say("wrote %s", line)
    finally:
        console.stop()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if received and received[0] == signal.SIGINT:
        final = " (final STATUS sent)" if services and _delivered(services[0].transport) else ""
        print(f"optitac-edge: interrupted: the service stopped cleanly{final}", file=sys.stderr)
        return EXIT_INTERRUPTED
    return 0  # SIGTERM / SIGHUP: a requested stop (systemd counts it as success)


def _delivered(transport: Transport) -> bool:
    """The link wrote something to the MCU (not the null link, not a port that never opened)."""
    return bool(transport.delivers and transport.counters.sent)


def _link_summary(transport: Transport) -> str:
    """What went over the link: messages written and those that could not be (from the link's own counters;
    frames handed to a port that was never there are not "sent")."""
    if not transport.delivers:
        return "no link: nothing was sent"
    c = transport.counters
    stats = transport.stats() if hasattr(transport, "stats") else {}
    absent = " (the port was never open: is it plugged in, is the name right?)" \
        if not c.sent and not stats.get("connected", True) else ""
    return (f"link: {c.sent} messages written, {c.send_errors} not sent{absent}, {c.received} received, "
            f"{c.rx_errors} bad, {c.reconnects} reconnects")


class StatusLine:
    """The live status line of ``run`` on a terminal, printed by its own thread: the frame loop only
    hands over a copy of the estimate when a line is due, and never waits on the terminal. The rate is
    over the last interval (the first camera's frames); the line is cut to the terminal's width so it never
    wraps. On a board of several sensors every named sensor offers its estimate and the line shows each
    briefly, in the order they first offered."""

    def __init__(self, period_s: float, link: str, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self._clock = clock
        self._period_ns = int(period_s * 1e9)
        self._link = link
        self._due_ns: dict[str, int] = {}
        self._last: tuple[int, int] | None = None  # (ns, frames) of the previous line
        self._latest: tuple[ContactEstimate | None, float | None] | None = None
        self._named: dict[str, ContactEstimate | None] = {}  # several sensors: each one's last copy, by name
        self._lead_name: str | None = None
        self._stats: ServiceStats | None = None
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._print_loop, name="optitac-status-line", daemon=True)

    def offer(self, est: ContactEstimate | None, stats: ServiceStats, name: str = "") -> None:
        """From a frame loop: keep a copy of ``est`` (a frame's primary estimate; None while the baseline is
        not ready) when a line is due. One camera's counters (the first that
        offers) make the rate (two cameras' made it -89.7 fps); a sensor of another camera is shown only when
        named."""
        if self._stats is None:
            self._stats = stats
        lead = stats is self._stats
        if not (lead or name):
            return
        now = self._clock()
        if now < self._due_ns.get(name, 0):
            return
        self._due_ns[name] = now + self._period_ns
        if name:
            with self._lock:
                self._named[name] = None if est is None else est.copy()
            if self._lead_name is None and lead:
                self._lead_name = name
            if name != self._lead_name:  # the line is drawn on the lead camera's first sensor's pace
                return
        fps = None
        if self._last is not None and now > self._last[0]:
            fps = (stats.frames - self._last[1]) * 1e9 / (now - self._last[0])
        self._last = (now, stats.frames)
        with self._lock:
            self._latest = (None if est is None else est.copy(), fps)
        self._wake.set()

    def _line(self) -> str | None:
        """The next line to draw (None: nothing new)."""
        with self._lock:
            latest, self._latest = self._latest, None
            named = list(self._named.items())
        if latest is None:
            return None
        if not named:
            return f"[{self._link}] {_status_line(*latest)}"
        rate = "  -.- fps" if latest[1] is None else f"{latest[1]:5.1f} fps"
        return f"[{self._link}] {rate}  " + " | ".join(_brief(n, e) for n, e in named)

    def _print_loop(self) -> None:
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            line = self._line()
            if line is not None:
                width = max(shutil.get_terminal_size((80, 24)).columns - 1, 20)
                with LIVE_LINE.lock:  # a log record clears the line first (it is drawn again here)
                    sys.stdout.write("\r\x1b[2K" + line[:width])
                    sys.stdout.flush()

    def __enter__(self) -> Self:
        LIVE_LINE.active = True
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=2.0)
        LIVE_LINE.active = False
        if not self._thread.is_alive():  # (a terminal stuck in write(): leave it alone)
            sys.stdout.write("\n")


def _run_service(args: argparse.Namespace, config: BoardConfig, stop: threading.Event,
                 say: Callable[..., None]) -> list[Service]:
    """Run the board's session; its services (the lead's first)."""
    from optitac_edge.service.session import BoardSession

    max_frames = args.frames
    link = "no link" if config.link.transport == "none" else config.link.transport
    with BoardSession(config, args.cal) as session, ExitStack() as stack:
        session.ride_out_stalls = bool(getattr(args, "ride_out_stalls", False))  # view: at a terminal
        stage_times: Path | None = getattr(args, "stage_times", None)
        session.stage_times = stage_times is not None
        # a status line on a terminal only: a pipe or journald gets the log, and nothing that could block
        line = stack.enter_context(StatusLine(0.1, link)) if sys.stdout.isatty() else None
        several = len(config.sensors) > 1
        if session.calibrates and logging.getLogger().getEffectiveLevel() > logging.INFO:
            say("calibrating fibers from the first rest frames...")  # else the service's log line says it
        bundle = session.bundle()
        STARTUP.mark("bundles")
        if getattr(args, "view", None):
            url = session.open_view(args.view)
            say(f"view: {url}")
            simulated_operator_for_the_view(session)
        via = link if link == "no link" else link + " link"
        if len(config.sensors) == 1:
            say(f"{int((~bundle.fibers.dead).sum())}/{bundle.layout.n_fibers} fibers; running "
                f"({config.camera.backend} camera, {via}; Ctrl-C to stop)")
        else:
            for name, group in session.bundles().items():
                for found in group:
                    b, where = found.bundle, list(found.sensor.sensor.region) or "the whole frame"
                    say(f"{found.sensor.label} on camera {name!r} ({where}): "
                        f"{int((~b.fibers.dead).sum())}/{b.layout.n_fibers} fibers")
            say(f"running {len(config.sensors)} sensors on {len(config.cameras)} camera(s) ({via}; Ctrl-C to stop)")

        def on_result(result: FrameResult, stats: ServiceStats) -> None:
            if line is None:
                return
            if not several:
                line.offer(result.primary if result.baseline_ready else None, stats)
                return
            # every sensor of this camera (its loop's own thread: their results are this frame's)
            service = next((s for s in session.services if s.stats is stats), None)
            for channel in () if service is None else service.channels:
                r = channel.pipeline.result
                line.offer(r.primary if r.baseline_ready else None, stats, channel.name)

        try:
            session.run(stop, duration_s=args.duration, on_result=on_result, max_frames=max_frames)
        finally:
            if stage_times is not None:
                _write_stage_times(stage_times, session.services)
        return session.services


def _write_stage_times(path: Path, services: list[Service]) -> None:
    """Every camera loop's stage times (``--stage-times``), the lead's first; the frames of the first second
    (at most half of them) left out: the camera's warm-up and the first packets."""
    out = []
    for service in services:
        times = service.stage_times
        if times is None:
            continue
        st = service.stats
        out.append({"camera": service.camera_name, "sensors": len(service.channels),
                    "fps": service.camera_config.fps, "frames_processed": st.frames,
                    "frames_dropped": st.frames_dropped, "kernel": "compiled" if service.pipeline.compiled else "numpy",
                    **times.summary(skip=min(int(service.camera_config.fps), times.frames // 2))})
    with AtomicFile(path) as f:
        f.write(json.dumps(out, indent=1) + "\n")


def simulated_operator_for_the_view(session: BoardSession) -> None:
    """On the simulated camera, a simulated operator does what the view's guided orientation asks (the
    simulator's own presses ignore its prompts)."""
    from optitac_edge.sim.camera import SimCamera
    from optitac_edge.sim.operator import PromptFollower

    camera = session.camera
    if isinstance(camera, SimCamera) and session.view is not None:
        operator = PromptFollower(camera.sensor.layout.radius_mm)
        previous = camera.program

        def follow(prompt: str) -> None:
            operator.follow(prompt)
            camera.press_with(operator if prompt else previous)

        session.view.on_prompt = follow
