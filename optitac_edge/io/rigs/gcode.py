"""A GRBL machine (3D printer, CNC, pen plotter) with the indenter on its tool head, over pyserial.

The port is opened with ``serial.serial_for_url`` (a device, ``socket://``,
``rfc2217://``...), exclusively. Protocol (GRBL 1.1, gnea/grbl doc/markdown/
interface.md and realtime_cmds.md; grblHAL adds states): a line command is
answered ``ok`` or ``error:N``; ``?`` asks for a status report
``<Idle|WPos:x,y,z|...>`` (or ``MPos`` with ``WCO``); ``!`` holds the feed,
Ctrl-X resets; ``ALARM:N`` reports an alarm, ``$H`` homes, ``$X`` unlocks.
Positions are work coordinates (``WPos``): set the work zero where you like.

Alarms, as the firmware has them (grbl/protocol.c, doc/csv/alarm_codes_en_US.csv):
a hard limit (``ALARM:1``) or a soft limit (``ALARM:2``) is a *critical event*:
GRBL answers nothing, status reports included, until a soft reset (Ctrl-X),
and forgets a reset sent in the 500 ms after the ``ALARM:N`` line
(``report_alarm_message``, grbl/report.c, waits 500 ms; then ``[MSG:Reset to
continue]`` and ``system_clear_exec_state_flag(EXEC_RESET)``, grbl/protocol.c),
so this backend resets after that message (and again until the banner comes);
after the reset it is still in alarm and
refuses G-code (``error:9``) until ``$X`` or ``$H``. After a soft limit the
position is kept (GRBL holds the feed before it stops), so this backend resets,
unlocks and retracts; after a hard limit or a reset in motion (``ALARM:3``) it
is lost, so the tip is not moved and the message says what to do.

The safety door (grbl/protocol.c) holds the feed: ``Door:1`` while open,
``Door:0`` once closed. A retract then resets (the position is kept once the
tip has stopped, grbl/motion_control.c ``mc_reset``), waits for the door to
be closed, resumes with nothing left to run, and lifts; a door left open is one
line, the tip not moved.

Reports are read as noise may have made them: a state word GRBL does not send
is a garbled report (polled again), and the work offset ``WCO`` (sent every 10
to 30 reports, grbl/report.c) is adopted only when two reports carry the same
(one flipped bit in it once put the start point 4 mm deep).
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from optitac_edge.errors import RigError
from optitac_edge.io.rigs.base import ABSURD_MM, GarbledReport, Rig, RigConfig, RigLimits, RigStatus, url_rest

#: GRBL's and grblHAL's state names -> :data:`~optitac_edge.io.rigs.base.STATES` (anything else: ``unknown``).
_STATES = {"idle": "idle", "run": "moving", "jog": "moving", "hold": "hold", "alarm": "alarm",
           "home": "homing", "door": "door", "check": "check", "sleep": "sleep", "tool": "tool"}
#: GRBL's alarm codes (grbl/doc/csv/alarm_codes_en_US.csv), for one-line messages.
ALARMS = {1: "hard limit: a limit switch was hit", 2: "soft limit: a target beyond the machine's travel",
          3: "reset while in motion", 4: "probe fail", 5: "probe fail", 6: "homing fail: reset",
          7: "homing fail: door", 8: "homing fail: pull off", 9: "homing fail: no switch",
          10: "homing fail: second switch"}
#: Alarms after which GRBL answers nothing until a soft reset (grbl/protocol.c: hard and soft limits).
CRITICAL_ALARMS = (1, 2)
#: Alarms after which the machine's position is lost (alarm_codes_en_US.csv: "re-homing is highly recommended").
POSITION_LOST = (1, 3)
#: What GRBL prints once it takes a reset after a critical alarm (grbl/report.c MESSAGE_CRITICAL_EVENT).
RESET_TO_CONTINUE = "[MSG:Reset to continue]"
#: How long to wait for it (GRBL: 500 ms after the alarm line), and between resets until the banner comes.
RESET_WAIT_S = 1.0
#: Status reports read at most to see the work offset twice (GRBL: every 10th when idle, grbl/config.h).
OFFSET_REPORTS = 25
#: Millimetres in an inch: with ``$13=1`` GRBL reports every coordinate in inches (grbl/print.c
#: ``printFloat_CoordValue``: ``n*INCH_PER_MM``, 4 decimals), MPos, WPos and WCO alike; ``G21`` changes how
#: commands are read, not reports.
MM_PER_INCH = 25.4
#: A feed hold's deceleration is waited for while the reported position still changes, up to this long (s);
#: it is taken as stopped once the position stood still for :data:`HOLD_STILL_S`.
HOLD_MAX_S = 120.0
HOLD_STILL_S = 10.0

log = logging.getLogger(__name__)


class _OffsetUnknown(GarbledReport):
    """A machine position while no two reports have agreed on the work offset yet."""


class GcodeRig(Rig):
    """A GRBL controller.

    Parameters
    ----------
    url : str
        Serial port or pyserial URL (what follows ``gcode://``).
    limits : RigLimits
    baudrate : int
    home : bool
        Home (``$H``) at start when the machine asks for it (else an alarm at start is an error).
    timeout_s : float
        How long a command may wait for ``ok`` (homing: 60 s).
    port : serial-like, optional
        An open port (tests); default ``serial.serial_for_url(url, exclusive=True)``.
    """

    #: How long a retract waits for an open safety door to be closed (s).
    door_wait_s = 30.0

    @classmethod
    def from_url(cls, url: str, config: RigConfig) -> GcodeRig:
        """``gcode://PORT`` (a device or a pyserial URL), with ``[rig]`` limits, ``baudrate`` and ``home``."""
        return cls(url_rest(url, "gcode"), config.limits(), baudrate=config.baudrate, home=config.home)

    def __init__(self, url: str, limits: RigLimits, baudrate: int = 115200, home: bool = False,
                 timeout_s: float = 2.0, port: Any = None, clock_ns: Callable[[], int] = time.monotonic_ns) -> None:
        super().__init__(limits, clock_ns=clock_ns)
        self.url = url
        self.timeout_s = timeout_s
        self._lines: deque[str] = deque()
        self._buffer = b""
        #: The work offset two reports agreed on (None: none yet), and one seen once.
        self._wco: tuple[float, float, float] | None = None
        self._wco_seen: tuple[float, float, float] | None = None
        #: The last report gave work positions (``WPos``): no offset is needed.
        self._work_positions = False
        #: GRBL said it takes a reset (:data:`RESET_TO_CONTINUE`) since the last critical alarm.
        self._reset_taken = True
        #: The last ``ALARM:N`` read and not yet cleared by ``$X`` / ``$H`` (0: none).
        self._alarm_code = 0
        #: A critical alarm was read and no reset sent since: GRBL answers nothing.
        self._silent = False
        #: Millimetres per reported unit (``$13``: 1, or 25.4 when GRBL reports inches).
        self.report_unit_mm = 1.0
        #: GRBL's settings as ``$$`` listed them at connect (``{10: "1", 13: "0", ...}``).
        self.settings: dict[int, str] = {}
        if port is None:
            import serial

            try:
                port = serial.serial_for_url(url, baudrate=baudrate, timeout=0.02, write_timeout=1.0,
                                             exclusive=True)
            except (serial.SerialException, ValueError, OSError) as exc:
                raise RigError(f"gcode rig {url}: cannot open the port ({exc})") from None
        self._port = port
        try:
            self._reset()
            self._read_settings()
            st = self.poll()
            if st.state == "alarm":
                if not home:
                    raise RigError(f"gcode rig {url}: the machine is in alarm ({st.alarm or 'locked'}); home it "
                                   "(rig.home = true, or $H) before collecting")
                self.command("$H", timeout_s=60.0)
                self._alarm_code = 0
            self.command("G21")  # mm
            self.command("G90")  # absolute
        except BaseException:
            self._port.close()
            raise

    # -- the wire ---------------------------------------------------------------------------

    def _write(self, data: bytes) -> None:
        try:
            self._port.write(data)
        except Exception as exc:  # noqa: BLE001 - pyserial raises SerialException / OSError / timeouts
            raise RigError(f"gcode rig {self.url}: connection lost ({exc})") from None

    def _readline(self, deadline: float) -> str | None:
        while not self._lines:
            if time.monotonic() > deadline:
                return None
            try:
                chunk = self._port.read(max(1, self._port.in_waiting))  # returns as soon as a byte is there
            except Exception as exc:  # noqa: BLE001
                raise RigError(f"gcode rig {self.url}: connection lost ({exc})") from None
            if not chunk:
                continue
            self._buffer += chunk
            *done, self._buffer = self._buffer.split(b"\n")
            for raw in done:
                line = raw.decode("ascii", "replace").strip()
                if line.startswith("ALARM:"):
                    self._alarm_code = _alarm_code(line)
                    if self._alarm_code in CRITICAL_ALARMS:
                        self._silent, self._reset_taken = True, False
                elif line == RESET_TO_CONTINUE:
                    self._reset_taken = True
                if line:
                    self._lines.append(line)
        return self._lines.popleft()

    def _alarm_error(self, code: int) -> RigError:
        what = ALARMS.get(code, "unknown alarm")
        if code in POSITION_LOST:
            todo = ("the machine's position is lost, so the tip was not moved: jog it clear of the skin, home the "
                    "machine ($H), then run the same command to continue")
        elif code == 2:
            todo = "the board's rig limits must lie inside the machine's travel ($130-$132)"
        else:
            todo = "reset the machine and home it ($H)"
        return RigError(f"gcode rig {self.url}: ALARM:{code} ({what}); {todo}")

    def _read_settings(self) -> None:
        """``$$``: the settings that change what reports mean (grbl/report.c ``report_grbl_settings``, one
        ``$N=V`` line each). ``$13=1``: coordinates in inches, converted here; ``$10``: MPos (bit 0 set) or
        WPos, both read. A listing without ``$13`` (not GRBL 1.1's) is refused: its units are unknown."""
        lines: list[str] = []
        self.command("$$", collect=lines)
        for line in lines:
            key, eq, value = line.partition("=")
            if eq and key.startswith("$") and key[1:].isdigit():
                self.settings[int(key[1:])] = value.strip()
        inches = self.settings.get(13)
        if inches not in ("0", "1"):
            raise RigError(f"gcode rig {self.url}: its settings ($$) do not say whether it reports millimetres or "
                           f"inches ($13 = {inches!r}); is it GRBL 1.1?")
        self.report_unit_mm = MM_PER_INCH if inches == "1" else 1.0
        if inches == "1":
            log.info("gcode rig %s reports inches ($13=1): its positions are converted to mm", self.url)

    def command(self, line: str, timeout_s: float | None = None, collect: list[str] | None = None) -> None:
        """Send one line and wait for ``ok`` (the lines before it into ``collect``, when given).

        Raises
        ------
        RigError
            On ``error:N``, an alarm, or no answer in time.
        """
        self._write(line.encode("ascii") + b"\n")
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        while True:
            reply = self._readline(deadline)
            if reply is None:
                if self._silent:
                    raise self._alarm_error(self._alarm_code)
                raise RigError(f"gcode rig {self.url}: no answer to {line!r} within "
                               f"{self.timeout_s if timeout_s is None else timeout_s:g} s")
            if reply == "ok":
                return
            if reply.startswith("error:"):
                raise RigError(f"gcode rig {self.url}: {line!r} refused ({reply})")
            if reply.startswith("ALARM:"):
                raise self._alarm_error(_alarm_code(reply))
            if collect is not None:
                collect.append(reply)

    def _reset(self) -> None:
        """Ctrl-X and wait for the ``Grbl`` banner (an ``ALARM:3`` before it is noted), then for the work offset.

        After a critical alarm, first wait for :data:`RESET_TO_CONTINUE` (GRBL forgets a reset before it);
        without a banner in :data:`RESET_WAIT_S`, reset again, until the timeout.
        """
        deadline = time.monotonic() + max(self.timeout_s, 3.0)
        if self._silent:
            wait = min(time.monotonic() + RESET_WAIT_S, deadline)
            while not self._reset_taken and self._readline(wait) is not None:
                pass
        while True:
            self._lines.clear()
            self._write(b"\x18")
            again = min(time.monotonic() + RESET_WAIT_S, deadline)
            line = self._readline(again)
            while line is not None and not line.startswith("Grbl"):
                line = self._readline(again)
            if line is not None:
                break
            if time.monotonic() >= deadline:
                raise RigError(f"gcode rig {self.url}: no GRBL answered (no banner after a reset)")
        self._silent, self._reset_taken = False, True
        self._settle_offset()

    def _settle_offset(self) -> None:
        """Read status reports until two agree on the work offset (a reset may change it: G92 is not kept)."""
        self._wco = self._wco_seen = None
        for _ in range(OFFSET_REPORTS):
            try:
                self._status()
            except _OffsetUnknown:  # the offset comes every 10th report
                continue
            except GarbledReport:
                self.garbled_reports += 1
                continue
            if self._wco is not None or self._work_positions:
                return
        if self._wco_seen is None:  # a GRBL built without the WCO field: machine positions are work positions
            log.warning("gcode rig %s: no work offset (WCO) in %d status reports; taking it as 0",
                        self.url, OFFSET_REPORTS)
            self._wco = (0.0, 0.0, 0.0)
            return
        raise RigError(f"gcode rig {self.url}: no two of {OFFSET_REPORTS} status reports agreed on the work "
                       "offset (WCO); check the cable")

    # -- Rig ---------------------------------------------------------------------------------

    def _move(self, xyz: tuple[float, float, float], feed_mm_s: float) -> None:
        x, y, z = xyz
        self.command(f"G1 X{x:.3f} Y{y:.3f} Z{z:.3f} F{feed_mm_s * 60.0:.1f}")

    def _lift(self, z_mm: float, feed_mm_s: float) -> None:
        """``G1 Z..`` alone: x and y stay where the machine is, whatever a report said."""
        self.limits.check_axis("z", z_mm)
        self.command(f"G1 Z{z_mm:.3f} F{feed_mm_s * 60.0:.1f}")

    def _status(self) -> RigStatus:
        if self._silent:  # GRBL answers nothing until a reset
            return RigStatus("alarm", (math.nan,) * 3, str(self._alarm_error(self._alarm_code)).split(": ", 1)[1])
        self._write(b"?")
        deadline = time.monotonic() + self.timeout_s
        while True:
            line = self._readline(deadline)
            if line is None:
                if self._silent:
                    return self._status()
                raise GarbledReport(f"gcode rig {self.url}: no status report within {self.timeout_s:g} s")
            if line.startswith("ALARM:"):
                return self._status()
            if line.startswith("<") and line.endswith(">"):
                return self._parse_status(line[1:-1])
            if not line.startswith(("[", "Grbl")):  # not a message or a banner: the report, garbled
                raise self._garbled(line)

    def _garbled(self, report: str) -> GarbledReport:
        """The error of a status report that is not one GRBL sends (noise on the line), the report escaped."""
        return GarbledReport(f"gcode rig {self.url}: garbled status report {report!r}")

    def _parse_status(self, body: str) -> RigStatus:
        fields = body.split("|")
        raw_state = fields[0]
        name = raw_state.split(":")[0].lower()
        if name not in _STATES:  # a word GRBL does not send: noise on the line
            raise GarbledReport(f"gcode rig {self.url}: status report in a state this program does not know ({raw_state!r})")
        state = _STATES[name]
        pos: tuple[float, float, float] | None = None
        machine = False
        for f in fields[1:]:
            key, _, value = f.partition(":")
            if key in ("MPos", "WPos", "WCO"):
                try:
                    xyz = tuple(float(v) for v in value.split(","))
                except ValueError:
                    raise self._garbled(f"<{body}>") from None
                if len(xyz) < 3 or not all(math.isfinite(v) and abs(v) < ABSURD_MM for v in xyz):
                    raise self._garbled(f"<{body}>")
                if key == "WCO":
                    self._offset_seen((xyz[0], xyz[1], xyz[2]))
                else:
                    pos, machine = (xyz[0], xyz[1], xyz[2]), key == "MPos"
        if pos is None:
            raise GarbledReport(f"gcode rig {self.url}: status report without a position {'<' + body + '>'!r}")
        self._work_positions = not machine
        if machine:
            if self._wco is None:
                raise _OffsetUnknown(f"gcode rig {self.url}: a machine position before the work offset is known")
            pos = (pos[0] - self._wco[0], pos[1] - self._wco[1], pos[2] - self._wco[2])
        k = self.report_unit_mm  # positions and offsets are kept as reported, converted here
        pos = (pos[0] * k, pos[1] * k, pos[2] * k)
        if not all(abs(v) < ABSURD_MM for v in pos):
            raise self._garbled(f"<{body}>")
        return RigStatus(state, pos, raw_state=raw_state)

    def _offset_seen(self, wco: tuple[float, float, float]) -> None:
        """A report's ``WCO``: adopted when it is the one seen before (else remembered until the next)."""
        if wco != self._wco:
            if wco == self._wco_seen:
                self._wco = wco
            self._wco_seen = wco

    def _stop(self) -> None:
        """Stop with the position kept, and leave the machine ready for a move.

        Not in alarm: feed hold, wait until stopped (``Hold:0``, or ``Door:0`` / ``Door:1`` when the safety
        door stopped it), then reset to drop the rest of the move; a door still open after the reset is
        waited for (:attr:`door_wait_s`), then the machine resumed with nothing left to run. In a soft-limit
        alarm (position kept): reset, then unlock (``$X``). After a hard limit or a reset in motion (position
        lost): reset, and refuse to move (the message says what the operator does).
        """
        if not self._silent:
            self._hold()
        self._reset()  # always: the rest of the move is dropped (a cycle start would resume it)
        st = self.poll()
        if st.state == "door":
            self._wait_for_the_door()
        elif st.state == "alarm":
            code = self._alarm_code
            if code not in (2,):
                raise self._alarm_error(code)
            self.command("$X")  # a soft limit: the position was kept
        self._alarm_code = 0
        self.command("G21")
        self.command("G90")

    def _hold(self) -> None:
        """Feed hold, and wait until the machine says it stopped (``Hold:0``; ``Door:0`` / ``Door:1``; idle; an
        alarm). A long deceleration is waited for while the reported position still changes
        (:data:`HOLD_STILL_S` without a change, at most :data:`HOLD_MAX_S`); then the caller resets all the
        same (a reset during the deceleration loses the position: ``ALARM:3``, said by the reset's caller)."""
        self._write(b"!")
        start = last_change = self.clock_ns() / 1e9  # the machine's time (a fake's virtual one in tests)
        last: tuple[float, float, float] | None = None
        while True:
            try:
                st = self.poll()
            except RigError:  # silent (an alarm whose line was lost?): the reset tells
                return
            if st.state in ("alarm", "idle") or st.raw_state.lower() in ("hold:0", "door:0", "door:1"):
                return
            now = self.clock_ns() / 1e9
            if last is None or math.dist(st.xyz_mm, last) > 1e-3:
                last, last_change = st.xyz_mm, now
            if now - last_change > HOLD_STILL_S or now - start > HOLD_MAX_S:
                log.warning("gcode rig %s: no stop reported %.0f s after a feed hold (%s at %s); resetting",
                            self.url, now - start, st.raw_state, st.xyz_mm)
                return
            time.sleep(0.02)

    def _wait_for_the_door(self) -> None:
        """After a reset in the door state (nothing left to run): wait until the door is closed (``Door:0``),
        then resume (``~``: GRBL leaves the door state, idle), before anything moves."""
        waited = 0.0
        while True:
            st = self.poll()
            if st.state != "door":
                return
            if st.raw_state.lower() == "door:0":
                self._write(b"~")
            elif waited > self.door_wait_s:
                raise RigError(f"gcode rig {self.url}: the safety door is open ({st.raw_state}); the tip was not "
                               "lifted: close the door, then run the same command to continue")
            self.sleep(0.05)
            waited += 0.05

    def _close_internal(self) -> None:
        self._port.close()


def _alarm_code(line: str) -> int:
    """N of ``ALARM:N`` (0 if garbled)."""
    try:
        return int(line.split(":", 1)[1])
    except (IndexError, ValueError):
        return 0
