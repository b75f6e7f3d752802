"""A fake GRBL 1.1 controller on a pty, following GRBL's protocol closely enough to test a rig backend.

Line commands are answered ``ok`` or ``error:N``; realtime bytes: ``?`` status
report ``<Idle|MPos:x,y,z|FS:f,0>``, ``!`` feed hold (``Hold:1`` then
``Hold:0``), ``~`` resume, Ctrl-X soft reset (a reset while moving, not held,
loses the position: ``ALARM:3``). ``$H`` homes, ``$X`` unlocks. Motion runs in
real time, ``speed`` times faster than commanded (to keep tests short); or,
with ``tick_s``, on a virtual clock that moves ``tick_s`` at each status
report the host asks for: a test that counts the frames of a move (one report
a frame) then counts the same on a busy machine.

Alarms follow the firmware (gnea/grbl: grbl/protocol.c, grbl/limits.c,
doc/markdown/realtime_cmds.md, doc/csv/alarm_codes_en_US.csv):

* a move beyond the travel is a soft limit: ``ALARM:2`` (the position kept);
  an injected hard limit stops at once: ``ALARM:1``. Both are critical events:
  *nothing* is answered -- no ``ok``, no status report (realtime_cmds.md: ``?``
  is executed "at any time, except ... when critical alarm (hard/soft limit
  error) is thrown") -- until Ctrl-X; and a Ctrl-X that comes too early is
  lost: ``report_alarm_message`` (grbl/report.c) waits 500 ms after the
  ``ALARM:N`` line (``delay_ms(500)``), then protocol_exec_rt_system()
  (grbl/protocol.c) prints ``[MSG:Reset to continue]`` and clears any reset
  that came before (``system_clear_exec_state_flag(EXEC_RESET)``); only a
  reset after that message is taken (here ``alarm_delay_s``, 0.5 s);
* the work offset ``WCO:x,y,z`` comes in the first report after a reset and
  then every 10th report when idle, every 30th when busy
  (``sys.report_wco_counter``, REPORT_WCO_REFRESH_IDLE_COUNT and _BUSY_COUNT
  in grbl/config.h, grbl/report.c); positions are machine positions ``MPos``;
* after the reset GRBL is still in alarm (its banner, then
  ``[MSG:'$H'|'$X' to unlock]``), answers status reports ``<Alarm|...>`` and
  refuses G-code with ``error:9`` until ``$X`` (``[MSG:Caution: Unlocked]``)
  or ``$H``.

The safety door (grbl/protocol.c protocol_exec_rt_system and
protocol_exec_rt_suspend, grbl/report.c): opening it holds the feed (``Door:2``
while the tip decelerates) and prints ``[MSG:Check Door]``; once stopped the
state is ``Door:1`` while it is open, ``Door:0`` once closed (ready to resume);
``~`` resumes the held move only when closed; a reset once stopped keeps the
position (mc_reset: not executing a hold) and flushes the move, and GRBL comes
back in the door state while the door is still open (protocol_main_loop checks
it at start), else idle. G-code sent in the door state waits for the resume.

Settings (``$$``, grbl/report.c ``report_grbl_settings``: one ``$N=V`` line each, then ``ok``): ``$10``
(status report mask; bit 0 set: ``MPos``, clear: ``WPos`` = machine position minus the work offset,
grbl/report.c ``report_realtime_status``) and ``$13`` (1: every reported coordinate in inches, 4 decimals,
grbl/print.c ``printFloat_CoordValue``; the offset too). A feed hold decelerates for ``hold_s`` (GRBL plans
the deceleration, grbl/stepper.c): the position still changes, the state is ``Hold:1``, and a reset meanwhile
loses the position (grbl/motion_control.c ``mc_reset``: ``STEP_CONTROL_EXECUTE_HOLD`` -> ``ALARM:3``); once
stopped (``Hold:0``) a reset keeps it and drops the rest of the move, which a cycle start (``~``) would
otherwise resume (grbl/protocol.c).

For the backend's robustness: :meth:`garble` replaces the next status reports
with given lines (noise on a real serial line), :meth:`set_state` reports a
state by name (grblHAL's ``Tool``, ``Door:1``, ``Sleep``).
"""

from __future__ import annotations

import math
import os
import pty
import re
import threading
import time
import tty

BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"


class FakeGrbl:
    def __init__(self, start=(100.6, 79.6, 5.0), travel=((0.0, 200.0), (0.0, 200.0), (-10.0, 40.0)),
                 speed: float = 1.0, locked: bool = False, tick_s: float | None = None,
                 alarm_delay_s: float = 0.5, wco=(0.0, 0.0, 0.0), report_inches: bool = False,
                 report_mpos: bool = True, hold_s: float = 0.0) -> None:
        self.tick_s = tick_s
        #: ``$13`` and ``$10``'s bit 0, and how long a feed hold decelerates (s).
        self.report_inches, self.report_mpos, self.hold_s = report_inches, report_mpos, hold_s
        self.alarm_delay_s = alarm_delay_s
        #: The work offset (G54 and G92): what the reports' ``WCO`` says, machine minus work position.
        self.wco = tuple(wco)
        self._wco_counter = 0  # the first report after a reset carries WCO
        #: After a critical alarm: a reset is taken (the ``Reset to continue`` message was sent).
        self._reset_armed = True
        #: Ctrl-X bytes lost because they came before ``Reset to continue``.
        self.lost_resets = 0
        self._ticks = 0
        self.master, self.slave = pty.openpty()
        tty.setraw(self.slave)
        self.port = os.ttyname(self.slave)
        self.travel = travel
        self.speed = speed
        self._lock = threading.Lock()
        self._from = self._to = tuple(start)
        self._t0 = self._t1 = self._clock()
        self._held_at: float | None = None
        self.state = "Alarm" if locked else "Idle"
        #: A critical alarm (hard or soft limit) was raised and no reset came since: nothing is answered.
        self.critical = False
        self._garbled: list[str] = []
        self._forced_state: str | None = None
        #: The safety door is open; the machine is in its door state (until resumed or reset with it closed).
        self.door_open = False
        self.in_door = False
        self._queued: tuple[tuple[float, float, float], float] | None = None
        self.lines: list[str] = []
        self.realtime: list[bytes] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    # -- motion ---------------------------------------------------------------------------------

    def position(self, now: float | None = None) -> tuple[float, float, float]:
        with self._lock:
            return self._position(self._clock() if now is None else now)

    def _position(self, now: float) -> tuple[float, float, float]:
        if self._held_at is not None:
            now = min(now, self._held_at + self.hold_s)
        if now >= self._t1 or self._t1 == self._t0:
            return self._to
        f = (now - self._t0) / (self._t1 - self._t0)
        return tuple(a + f * (b - a) for a, b in zip(self._from, self._to))  # type: ignore[return-value]

    def _moving(self, now: float) -> bool:
        return self._held_at is None and now < self._t1

    def _decelerating(self, now: float) -> bool:
        """A feed hold not yet complete (GRBL's STEP_CONTROL_EXECUTE_HOLD)."""
        return (self._held_at is not None and now - self._held_at < max(self.hold_s, 0.02)
                and self._held_at < self._t1)

    def _status(self) -> bytes:
        now = self._clock()
        with self._lock:
            pos = self._position(now)
            if self._garbled:
                return (self._garbled.pop(0) + "\r\n").encode()
            wco = ""
            if self._wco_counter == 0:
                wco = "|WCO:" + ",".join(f"{v:.3f}" for v in self.wco)
                self._wco_counter = 30 if self._moving(now) else 10
            self._wco_counter -= 1
            if self.state == "Alarm":
                state = "Alarm"
            elif self.in_door:
                stopping = self._held_at is not None and now - self._held_at <= 0.02 and now < self._t1
                state = "Door:2" if stopping else "Door:1" if self.door_open else "Door:0"
            elif self._forced_state is not None:
                state = self._forced_state
            elif self._held_at is not None:
                state = "Hold:1" if self._decelerating(now) else "Hold:0"
            else:
                state = "Run" if self._moving(now) else "Idle"
        k, digits = (1 / 25.4, 4) if self.report_inches else (1.0, 3)
        if wco:
            wco = "|WCO:" + ",".join(f"{v * k:.{digits}f}" for v in self.wco)
        m = [(p + o if self.report_mpos else p) * k for p, o in zip(pos, self.wco)]  # moves in work coordinates
        kind = "MPos" if self.report_mpos else "WPos"
        return f"<{state}|{kind}:{m[0]:.{digits}f},{m[1]:.{digits}f},{m[2]:.{digits}f}|FS:0,0{wco}>\r\n".encode()

    # -- the wire -------------------------------------------------------------------------------

    def _send(self, data: bytes) -> None:
        try:
            os.write(self.master, data)
        except OSError:
            pass

    def garble(self, *reports: str) -> None:
        """Answer the next ``?`` with these lines instead of the status report, one each."""
        with self._lock:
            self._garbled.extend(reports)

    def set_state(self, state: str | None) -> None:
        """Report this state name (e.g. ``Tool``, ``Door:1``) instead of Idle/Run; None: back to normal."""
        with self._lock:
            self._forced_state = state

    def open_door(self) -> None:
        """Open the safety door: a feed hold, then the door state."""
        with self._lock:
            now = self._clock()
            if self._moving(now):
                self._held_at = now
            self.door_open = self.in_door = True
        self._send(b"[MSG:Check Door]\r\n")

    def close_door(self) -> None:
        with self._lock:
            self.door_open = False

    def inject_alarm(self, code: int = 1) -> None:
        """Raise ``ALARM:code`` now: motion stops where it is (a hard limit: the switch halts it at once)."""
        with self._lock:
            now = self._clock()
            self._from = self._to = self._position(now)
            self._t0 = self._t1 = now
            self._held_at = None
            self.state = "Alarm"
            self.critical = code in (1, 2)
            self._reset_armed = not self.critical
        self._send(f"ALARM:{code}\r\n".encode())
        if code in (1, 2):
            timer = threading.Timer(self.alarm_delay_s, self._reset_to_continue)
            timer.daemon = True
            timer.start()

    def _reset_to_continue(self) -> None:
        """500 ms after the alarm: the message, and a reset sent before it is forgotten (grbl/protocol.c)."""
        self._send(b"[MSG:Reset to continue]\r\n")
        with self._lock:
            self._reset_armed = True

    def _serve(self) -> None:
        line = b""
        while not self._stop.is_set():
            try:
                data = os.read(self.master, 256)
            except OSError:
                return
            for byte in data:
                b = bytes([byte])
                if b in (b"?", b"!", b"~", b"\x18"):
                    self.realtime.append(b)
                    if self.critical and b != b"\x18":
                        continue  # a critical event blocks everything but a reset
                    if self.critical and not self._reset_armed:
                        self.lost_resets += 1  # cleared by system_clear_exec_state_flag(EXEC_RESET)
                        continue
                    if b == b"\x18":
                        line = b""  # serial_reset_read_buffer()
                    self._realtime(b)
                elif self.critical:
                    continue
                elif b in (b"\n", b"\r"):
                    if line.strip():
                        self._line(line.decode("ascii", "replace").strip())
                    line = b""
                else:
                    line += b

    def _clock(self) -> float:
        return time.monotonic() if self.tick_s is None else self._ticks * self.tick_s

    def now_ns(self) -> int:
        """The machine's clock (with ``tick_s``: its virtual one), ns: a rig's ``clock_ns`` in tests."""
        return round(self._clock() * 1e9)

    def _realtime(self, b: bytes) -> None:
        if b == b"?" and self.tick_s is not None:
            self._ticks += 1
        now = self._clock()
        if b == b"?":
            self._send(self._status())
        elif b == b"!":
            with self._lock:
                if self._moving(now) and not self.in_door:
                    self._held_at = now
        elif b == b"~":
            with self._lock:
                if self.in_door:
                    if self.door_open:
                        return  # the door blocks a resume
                    self.in_door = False
                    if self._queued is not None and self._held_at is None:
                        target, feed = self._queued
                        self._queued = None
                        self._start_move(self._position(now), target, feed, now)
                        return
                if self._held_at is not None:
                    pos = self._position(now)
                    self._held_at = None
                    self._start_move(pos, self._to, 1.0, now)
        elif b == b"\x18":
            with self._lock:
                lost = self._moving(now) or self._decelerating(now)
                pos = self._position(now)
                self._from = self._to = pos
                self._t0 = self._t1 = now
                self._held_at = None
                self.critical = False
                self._wco_counter = 0
                self._queued = None
                self.in_door = self.door_open  # protocol_main_loop: a door still open is the door state again
                if lost:
                    self.state = "Alarm"
            if lost:
                self._send(b"ALARM:3\r\n")
            self._send(BANNER)
            if self.state == "Alarm":
                self._send(b"[MSG:'$H'|'$X' to unlock]\r\n")

    def _start_move(self, a, b, feed_mm_min: float, now: float) -> None:
        self._from, self._to = tuple(a), tuple(b)
        dist = math.dist(a, b)
        self._t0 = now
        self._t1 = now + (dist / (feed_mm_min / 60.0) / self.speed if feed_mm_min > 0 else 0.0)
        self._feed = feed_mm_min

    def _line(self, text: str) -> None:
        self.lines.append(text)
        upper = text.upper()
        if upper == "$H":
            with self._lock:
                self.state = "Idle"
            self._send(b"ok\r\n")
            return
        if upper == "$$":
            mask = 1 if self.report_mpos else 0
            listing = f"$0=10\r\n$1=25\r\n$10={mask}\r\n$11=0.010\r\n$12=0.002\r\n$13={int(self.report_inches)}\r\n"
            self._send(listing.encode() + b"ok\r\n")
            return
        if upper == "$X":
            with self._lock:
                self.state = "Idle"
            self._send(b"[MSG:Caution: Unlocked]\r\nok\r\n")
            return
        if self.state == "Alarm":
            self._send(b"error:9\r\n")  # G-code locked out during alarm
            return
        if re.search(r"[A-Z](?![-+]?[0-9]*\.?[0-9])", upper.replace(" ", "")):
            self._send(b"error:2\r\n")  # a word without a number GRBL reads (read_float: no 'nan', no exponent)
            return
        words = dict(re.findall(r"([A-Z])\s*([-+]?[0-9]*\.?[0-9]+)", upper))
        if upper.startswith(("G21", "G90", "G4")) and "X" not in words:
            self._send(b"ok\r\n")
            return
        if upper.startswith(("G0", "G1")):
            now = self._clock()
            with self._lock:
                pos = self._position(now)
                target = tuple(float(words.get(axis, pos[k])) for k, axis in enumerate("XYZ"))
                feed = float(words.get("F", getattr(self, "_feed", 600.0)))
                beyond = any(not lo <= v <= hi for v, (lo, hi) in zip(target, self.travel))
                if not beyond and self.in_door:
                    self._queued = (target, feed)  # planned; runs on the resume
                elif not beyond:
                    self._start_move(pos, target, feed, now)
            if beyond:  # limits_soft_check(): the position is kept, then the critical event
                self.inject_alarm(2)
                return
            self._send(b"ok\r\n")
            return
        self._send(b"error:20\r\n")  # unsupported or invalid g-code command

    def close(self) -> None:
        self._stop.set()
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass
