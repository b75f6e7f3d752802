"""Hashes of what a refactoring must leave byte-identical: bundles, replays, the wire and the network.

Usage::

    python tools/behaviour_hashes.py OUT.txt [--workdir DIR]

Simulated recordings (made once in ``--workdir``) are calibrated with the CLI
(fibers, centroid, width, shapes, depth) and replayed into contacts CSVs; then
the service runs on a virtual clock over 1 to 4 simultaneous presses and a
recording, while a scripted MCU switches protocols, changes the rate divider,
stops and starts streaming, tares and sets the threshold. Every message the
transport is handed (encoded with the wire encoders) and every message the
network publisher publishes (its wall clock fixed) is hashed. Run it before and
after a change and ``diff`` the two files: every line must be equal. The
bundle's creation time and digest are left out (they change every run).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

import numpy as np

#: Recordings: name -> the ``sim`` arguments.
RECORDINGS = {"rest": ["--scenario", "rest", "--seed", "2"], "demo": ["--scenario", "demo", "--seed", "1"],
              "rgb": ["--scenario", "demo", "--seed", "3", "--rgb"], "seen": ["--scenario", "seen", "--seed", "4"],
              "widths": ["--scenario", "widths", "--seed", "5"], "shapes": ["--scenario", "shapes", "--seed", "6"],
              "depths": ["--scenario", "depths", "--seed", "7"], "drift": ["--scenario", "drift", "--seed", "8"],
              "unseen2": ["--scenario", "unseen", "--seed", "9", "--day", "2"]}
#: What the scripted MCU says before the loop's n-th command poll.
SCRIPT = {150: ("SET_PROTOCOL", {"version": 2}), 400: ("STREAM", {"stream_on": True, "rate_divider": 3}),
          600: ("STREAM", {"stream_on": False}), 660: ("STREAM", {"stream_on": True}), 800: ("TARE", {}),
          900: ("SET_PROTOCOL", {"version": 1}), 1000: ("SET_PROTOCOL", {"version": 2}),
          1100: ("STREAM", {"stream_on": True, "rate_divider": 2}), 1180: ("SET_THRESHOLD", {"threshold": 300})}


def cli(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "optitac_edge.cli", "-q", *args], check=True, stdout=subprocess.DEVNULL)


def digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def bundle_lines(cal: Path) -> list[str]:
    """Every array of the bundle, and its meta without the creation time."""
    out = []
    with np.load(cal, allow_pickle=False) as z:
        for key in sorted(z.files):
            if key == "digest":
                continue
            data = z[key].tobytes()
            if key == "meta":
                meta = json.loads(data.decode())
                meta.pop("created_utc", None)
                data = json.dumps(meta, sort_keys=True).encode()
            out.append(f"bundle {key} {digest(data)}")
    return out


def service_lines(cal: Path, demo: Path) -> list[str]:
    """The scripted service run, over a transport and a publisher that keep what they are handed."""
    try:  # a tree from before the config package (to compare with)
        from optitac_edge.service.board_config import load_board_config
    except ImportError:
        from optitac_edge.config import load_board_config
    from optitac_edge.io.bundle_file import load_bundle
    from optitac_edge.io.cameras.base import Camera, CapturedFrame
    from optitac_edge.io.clock import VirtualClock
    from optitac_edge.io.protocol import wire
    from optitac_edge.io.protocol.messages import Command, CommandType
    from optitac_edge.io.publishers.base import Publisher
    from optitac_edge.io.recording import Recording
    from optitac_edge.io.transports.base import Transport
    from optitac_edge.service import network
    from optitac_edge.service.loop import Service
    from optitac_edge.service.network import NetworkOutput, NetworkSensor
    from optitac_edge.sim.multi_press import multi_press_frames

    bundle = load_bundle(cal)
    frames: list[np.ndarray] = []
    for n, count in ((1, 60), (2, 80), (3, 50), (4, 70), (2, 40)):
        frames += multi_press_frames(n, count, bundle.baseline_frames, layout=bundle.layout, seed=n)
    rec = Recording(demo)
    frames += [np.ascontiguousarray(rec.frames[i]) for i in range(len(rec.frames))]
    frames *= 2
    script = {k: Command(CommandType[name], 0, **kw) for k, (name, kw) in SCRIPT.items()}

    class Frames(Camera):
        pixel_format, fps = "gray", 240.0

        def __init__(self, clock: VirtualClock) -> None:
            super().__init__()
            self.height, self.width = frames[0].shape
            self.i, self.clock = 0, clock

        def _read_internal(self, timeout_s: float) -> CapturedFrame | None:
            if self.i >= len(frames):
                return None
            self.i += 1
            self.clock.advance(1 / 240)
            return CapturedFrame(frames[self.i - 1], self.clock.monotonic_ns(), self.i)

        def _close_internal(self) -> None:
            pass

    class Kept(Transport):
        protocols = (1, 2)

        def __init__(self, alongside: bool) -> None:
            super().__init__()
            self.from_start = frozenset({1, 2}) if alongside else frozenset()
            self.out, self.polls = [], 0

        def send(self, packet: Any) -> None:  # packed by the serial packer, as the wire has them
            payload, kind = packet.frames[0][1], packet.kind
            if kind is wire.MsgType.CONTACT:
                self.out.append(b"C" + payload + packet.t_us.to_bytes(8, "little"))
            elif kind is wire.MsgType.CONTACT2:
                self.out.append(b"D" + payload)
            elif kind is wire.MsgType.RELEASE:
                self.out.append(b"R" + payload)
            elif kind is wire.MsgType.STATUS:
                m = wire.decode_status(payload)
                self.out.append(b"S" + m.state.to_bytes(2, "little") + m.frames_dropped.to_bytes(4, "little"))

        def poll_commands(self) -> list[Command]:
            self.polls += 1
            return [script[self.polls]] if self.polls in script else []

        def _close_internal(self) -> None:
            pass

    class KeptPublisher(Publisher):
        namespace = ""

        def __init__(self) -> None:
            super().__init__()
            self.out: list[bytes] = []

        def advertise(self, topic: str, type_name: str) -> int:
            return len(topic)

        def publish(self, handle: int, payload: bytes, source_ns: int) -> None:
            self.out.append(handle.to_bytes(2, "little") + payload)

        @property
        def where(self) -> str:
            return "kept"

        def _close_internal(self) -> None:
            pass

    class FixedTime:  # the network's wall clock: the same every run
        time_ns = staticmethod(lambda: 10**18)
        monotonic_ns = staticmethod(lambda: 0)

    network.time = FixedTime  # type: ignore[assignment]
    logging.getLogger("optitac_edge").setLevel(logging.ERROR)  # the scripted tare over a press is expected
    out = []
    for alongside in (False, True):
        clock = VirtualClock()
        config = load_board_config("sim", env={}, overrides={"status.period_s": 0.25})
        transport, publisher = Kept(alongside), KeptPublisher()
        service = Service(config, bundle, Frames(clock), transport, clock=clock)
        xy = bundle.layout.xy_mm
        service.network = NetworkOutput(publisher, [NetworkSensor(0, "sensor", xy[:, 0], xy[:, 1],
                                                                  bundle.fibers.dead, "c0ffee")], queue=100_000)
        stats = service.run(threading.Event())
        service.network.close()
        kinds: dict[bytes, int] = {}
        for m in transport.out:
            kinds[m[:1]] = kinds.get(m[:1], 0) + 1
        out.append(f"service alongside={alongside} frames={stats.frames} messages={sorted(kinds.items())} "
                   f"wire={digest(b''.join(transport.out))}")
        out.append(f"network alongside={alongside} messages={len(publisher.out)} {digest(b''.join(publisher.out))}")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("output", type=Path)
    ap.add_argument("--workdir", type=Path, default=Path(tempfile.gettempdir()) / "optitac-behaviour")
    args = ap.parse_args()
    work = args.workdir
    work.mkdir(parents=True, exist_ok=True)
    for name, sim_args in RECORDINGS.items():
        if not (work / name).exists():
            cli("sim", str(work / name), *sim_args)
    cal, rgb_cal = work / "cal.npz", work / "cal-rgb.npz"
    for path in (cal, rgb_cal):
        path.unlink(missing_ok=True)
    cli("calibrate", "fibers", str(work / "rest"), "-o", str(cal))
    for step, rec in (("centroid", "seen"), ("width", "widths"), ("shapes", "shapes"), ("depth", "depths")):
        cli("calibrate", step, str(work / rec), "--cal", str(cal))
    cli("calibrate", "fibers", str(work / "rgb"), "-o", str(rgb_cal))
    lines = bundle_lines(cal)
    for name in ("demo", "rgb", "unseen2", "drift", "shapes"):
        csv = work / f"{name}.csv"
        cli("replay", str(work / name), "--cal", str(rgb_cal if name == "rgb" else cal), "-o", str(csv))
        lines.append(f"replay {name} {digest(csv.read_bytes())} rows={csv.read_text().count(chr(10))}")
    lines += service_lines(cal, work / "demo")
    args.output.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.output}: {len(lines)} lines")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
