"""``optitac-edge soak``: the whole service loop on the simulator with injected faults, for minutes.

The simulated camera misbehaves on purpose (every kind of
:data:`~optitac_edge.sim.faults.FAULT_KINDS`, at ``fault_rate`` per read) and
the serial link (``loop://``, pyserial's loopback) is unplugged every
:data:`UNPLUG_EVERY_S` of the service's time. The verdict: every injected
fault counted, no exception out of the loop, the process's memory flat.

With ``virtual_time`` the service, the camera and the faults run on a
:class:`~optitac_edge.io.clock.VirtualClock`: as fast as the machine
computes, and the same seed gives the same frames, faults and reopens on any
machine (the serial link's own threads still run in real time, so its
counters are not part of that promise).
"""

from __future__ import annotations

import logging
import resource
import threading
import tracemalloc
from collections import Counter
from dataclasses import dataclass, field
from itertools import count
from typing import Any

import serial

from optitac_edge.config import load_board_config
from optitac_edge.core.frame_result import FrameResult
from optitac_edge.io.clock import SYSTEM_CLOCK, Clock, VirtualClock
from optitac_edge.io.transports.serial import SerialTransport
from optitac_edge.service.bundles import calibrate_from_camera
from optitac_edge.service.loop import Service, ServiceStats
from optitac_edge.sim.camera import SimCamera
from optitac_edge.sim.faults import FaultInjector

log = logging.getLogger(__name__)

#: The serial link is unplugged this often (service time), s.
UNPLUG_EVERY_S = 7.0
#: Max RSS is sampled this often (service time), s; the first sample is after warm-up.
RSS_EVERY_S = 5.0
#: Largest max-RSS growth accepted, kB.
MAX_RSS_GROWTH_KB = 20_000


@dataclass
class SoakResult:
    """What one soak run saw."""

    seconds: float
    stats: ServiceStats
    injected: Counter[str]
    unplugs: int
    link: dict[str, Any]
    unhandled: int
    rss_kb: list[int] = field(default_factory=list)
    heap_kb: int = 0
    heap_peak_kb: int = 0

    @property
    def rss_growth_kb(self) -> int:
        """Max RSS at the end minus after warm-up (the second sample), kB."""
        if not self.rss_kb:
            return 0
        return self.rss_kb[-1] - self.rss_kb[min(1, len(self.rss_kb) - 1)]

    @property
    def ok(self) -> bool:
        """Every fault counted, frames processed, nothing unhandled, memory flat."""
        recovered = self.stats.camera_errors == sum(self.injected.values()) and self.stats.frames > 0
        return recovered and self.unhandled == 0 and self.rss_growth_kb < MAX_RSS_GROWTH_KB

    def summary(self) -> str:
        """One line for a person (the CLI prints it)."""
        st = self.stats
        kinds = " ".join(f"{k}={v}" for k, v in sorted(self.injected.items()))
        first = self.rss_kb[min(1, len(self.rss_kb) - 1)] if self.rss_kb else 0
        last = self.rss_kb[-1] if self.rss_kb else 0
        return (f"soak {self.seconds:.0f} s: frames {st.frames}, faults injected {sum(self.injected.values())} "
                f"({kinds}), camera faults counted {st.camera_errors}, reopens {st.reopens} "
                f"(failed {st.reopen_failures}), serial unplugs {self.unplugs}, reconnects "
                f"{self.link.get('reconnects', 0)}, link errors "
                f"{self.link.get('send_errors', 0) + self.link.get('rx_errors', 0)}, "
                f"unhandled exceptions {self.unhandled}, max RSS {first} -> {last} kB, "
                f"python heap {self.heap_kb} kB (peak {self.heap_peak_kb} kB): {'OK' if self.ok else 'FAILED'}")


def run_soak(minutes: float, fault_rate: float = 0.01, seed: int = 0, fps: float = 60.0,
             virtual_time: bool = False, stop: threading.Event | None = None) -> SoakResult:
    """Run the soak for ``minutes`` of service time (see the module docstring).

    Raises
    ------
    ValueError
        If ``minutes`` is not positive or ``fault_rate`` is outside 0..1.
    """
    if not minutes > 0 or not 0 <= fault_rate <= 1:
        raise ValueError("minutes must be positive and the fault rate in 0..1")
    clock: Clock = VirtualClock() if virtual_time else SYSTEM_CLOCK
    config = load_board_config("sim", env={}, overrides={"camera.fps": fps, "status.period_s": 0.5,
                                                         "camera.timeout_s": 0.5})
    inj = FaultInjector(rate=fault_rate, seed=seed, gone_s=0.5, max_wait_s=0.1, clock=clock)
    seeds = count(seed + 1)

    def open_sim() -> SimCamera:
        if virtual_time:
            return SimCamera(fps=fps, realtime=False, seed=next(seeds), rest_frames=10, clock=clock)
        return SimCamera(fps=fps, realtime=True, seed=next(seeds), rest_frames=10)

    with open_sim() as cam:
        bundle = calibrate_from_camera(config, cam)
    ports: list[Any] = []  # the ports the transport opened, the newest last

    def open_port() -> Any:
        ports.append(serial.serial_for_url("loop://", timeout=0.05, write_timeout=0.2))
        return ports[-1]

    def unplug() -> int:
        """Close the transport's port under it: its next write or read fails as if the adapter vanished."""
        if not ports or not ports[-1].is_open:
            return 0
        ports[-1].close()
        return 1

    transport = SerialTransport("loop://", open_port=open_port)
    stop = stop or threading.Event()
    start_ns = clock.monotonic_ns()
    due = {"unplug": start_ns + int(UNPLUG_EVERY_S * 1e9), "rss": start_ns}
    result = SoakResult(0.0, ServiceStats(), inj.injected, 0, {}, 0)

    def on_result(_result: FrameResult, stats: ServiceStats) -> None:
        now = clock.monotonic_ns()
        if now >= due["rss"]:
            result.rss_kb.append(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
            due["rss"] = now + int(RSS_EVERY_S * 1e9)
        if now >= due["unplug"]:
            result.unplugs += unplug()
            due["unplug"] = now + int(UNPLUG_EVERY_S * 1e9)

    tracemalloc.start()
    service = Service(config, bundle, None, transport, camera_factory=inj.factory(open_sim), clock=clock)
    try:
        result.stats = service.run(stop, duration_s=minutes * 60, on_result=on_result)
    except Exception as exc:  # noqa: BLE001 - counted: the soak's verdict
        result.unhandled += 1
        log.error("unhandled exception: %s: %s", type(exc).__name__, exc)
        result.stats = service.stats
    finally:
        transport.close()
        current, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    result.link = transport.stats()
    result.heap_kb, result.heap_peak_kb = current // 1024, peak // 1024
    result.seconds = (clock.monotonic_ns() - start_ns) / 1e9
    return result
