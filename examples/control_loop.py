#!/usr/bin/env python3
"""A control loop slower than the camera, on the public API's background reader, and what it saw.

The sensor reads every frame in its own thread (``Sensor.start``); the loop takes the newest reading at its
own rate (``Sensor.latest``), never waiting for a frame. At the end it prints, one figure a line:

- how many ticks got the newest reading: one at least as new as every frame processed before the tick asked
  (``status().frames`` just before ``latest()``), and how many ticks got none (no new frame since the last);
- the count check: frames processed == readings taken + ``status().unread`` (nothing lost silently), and the
  frames the camera itself lost (``status().dropped``: the reader fell behind the camera), while the loop ran
  and before it (while the sensor opened: its bundle and kernel plan are made with the camera streaming);
- the threads the sensor left behind after ``close()`` (none expected).

    python examples/control_loop.py                        # 60 s at 20 Hz, the simulated sensor at 240 fps
    python examples/control_loop.py --seconds 5 --hz 50 --scenario slide
    python examples/control_loop.py --board rpi5-gs --cal /var/lib/optitac-edge/sensor0.npz

Exit status 1 when a tick got an older reading, the counts disagree or a thread is left.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time

import optitac_edge as ot


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--board", default="sim", help="a packaged board or a board config file (default: sim)")
    p.add_argument("--cal", default=None, help="a calibration bundle (default: the board's)")
    p.add_argument("--seconds", type=float, default=60.0, help="how long the loop runs (default 60)")
    p.add_argument("--hz", type=float, default=20.0, help="the loop's rate (default 20)")
    p.add_argument("--fps", type=float, default=240.0, help="the camera's rate (default 240)")
    p.add_argument("--scenario", default=None, help="the simulated board's presses: presses, slide, vibrate")
    args = p.parse_args(argv)
    settings: dict[str, object] = {"camera.fps": args.fps}
    if args.scenario:
        settings["camera.options.scenario"] = args.scenario
    before = set(threading.enumerate())
    ticks = newest = none = sliding = 0
    try:
        with ot.open_sensor(args.board, cal=args.cal, settings=settings) as sensor:
            sensor.tare(wait_s=10.0)  # the rest light before the loop starts (nothing touches the skin)
            dropped_before = sensor.status().dropped  # while the sensor opened: no one read its camera
            sensor.start()
            period, start = 1.0 / args.hz, time.monotonic()
            for ticks in range(1, round(args.seconds * args.hz) + 1):  # tick k at start + k / hz
                time.sleep(max(start + (ticks - 1) * period - time.monotonic(), 0.0))
                processed = sensor.status().frames
                reading = sensor.latest()
                if reading is None:
                    none += 1
                    continue
                newest += reading.frame >= processed - 1
                sliding += any(c.sliding for c in reading.contacts)
            sensor.stop()
            status = sensor.status()
    except ot.OptiTacError as exc:
        print(f"control_loop: {exc}", file=sys.stderr)
        return 2
    taken = ticks - none
    left = sorted(t.name for t in set(threading.enumerate()) - before if t.is_alive())
    print(f"loop: {ticks} ticks at {args.hz:g} Hz over {args.seconds:g} s, camera at {args.fps:g} fps")
    print(f"newest reading: {newest} of {taken} readings taken; {none} ticks with no new frame; "
          f"{sliding} with a sliding contact")
    print(f"frames processed {status.frames} = taken {taken} + unread {status.unread}: "
          f"{'yes' if status.frames == taken + status.unread else 'NO'}; camera dropped "
          f"{status.dropped - dropped_before} while the loop ran ({dropped_before} while the sensor opened), "
          f"skipped {status.skipped}")
    print(f"threads left after close(): {len(left)}{' (' + ', '.join(left) + ')' if left else ''}")
    return 0 if newest == taken and status.frames == taken + status.unread and not left else 1


if __name__ == "__main__":
    raise SystemExit(main())
