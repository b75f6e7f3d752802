"""A GRBL machine (3D printer, CNC, pen plotter) with the indenter on its tool head, over pyserial.

The port is opened with ``serial.serial_for_url`` (a device, ``socket://``,
``rfc2217://``...), exclusively. Protocol (GRBL 1.1): a line command is
answered ``ok`` or ``error:N``; ``?`` asks for a status report
``<Idle|WPos:x,y,z|...>`` (or ``MPos`` with ``WCO``); ``!`` holds the feed,
Ctrl-X resets; ``ALARM:N`` reports an alarm, ``$H`` homes, ``$X`` unlocks.
Positions are work coordinates (``WPos``): set the work zero where you like.
"""

from __future__ import annotations

import time
from collections import deque
from typing import Any

from optitac_edge.errors import RigError
from optitac_edge.io.rigs.base import Rig, RigLimits, RigStatus

#: GRBL state names -> :data:`~optitac_edge.io.rigs.base.STATES`.
_STATES = {"idle": "idle", "run": "moving", "jog": "moving", "hold": "hold", "alarm": "alarm",
           "home": "homing", "door": "hold", "check": "hold", "sleep": "hold"}
#: GRBL's alarm codes (grbl/doc/csv/alarm_codes_en_US.csv), for one-line messages.
ALARMS = {1: "hard limit triggered", 2: "soft limit: the target is beyond the machine's travel",
          3: "reset while in motion: position lost, home again", 4: "probe fail", 5: "probe fail",
          6: "homing fail: reset", 7: "homing fail: door", 8: "homing fail: pull off", 9: "homing fail: no switch"}


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

    def __init__(self, url: str, limits: RigLimits, baudrate: int = 115200, home: bool = False,
                 timeout_s: float = 2.0, port: Any = None) -> None:
        super().__init__(limits)
        self.url = url
        self.timeout_s = timeout_s
        self._lines: deque[str] = deque()
        self._buffer = b""
        self._wco = (0.0, 0.0, 0.0)
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
            st = self._status()
            if st.state == "alarm":
                if not home:
                    raise RigError(f"gcode rig {url}: the machine is in alarm ({st.alarm or 'locked'}); home it "
                                   "(rig.home = true, or $H) before collecting")
                self.command("$H", timeout_s=60.0)
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
                if line:
                    self._lines.append(line)
        return self._lines.popleft()

    def _alarm(self, line: str) -> RigError:
        try:
            code = int(line.split(":", 1)[1])
        except (IndexError, ValueError):
            code = 0
        return RigError(f"gcode rig {self.url}: ALARM:{code} ({ALARMS.get(code, 'unknown alarm')})")

    def command(self, line: str, timeout_s: float | None = None) -> None:
        """Send one line and wait for ``ok``.

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
                raise RigError(f"gcode rig {self.url}: no answer to {line!r} within "
                               f"{self.timeout_s if timeout_s is None else timeout_s:g} s")
            if reply == "ok":
                return
            if reply.startswith("error:"):
                raise RigError(f"gcode rig {self.url}: {line!r} refused ({reply})")
            if reply.startswith("ALARM:"):
                raise self._alarm(reply)

    def _reset(self) -> None:
        """Ctrl-X and wait for the ``Grbl`` banner."""
        self._lines.clear()
        self._write(b"\x18")
        deadline = time.monotonic() + max(self.timeout_s, 3.0)
        while True:
            line = self._readline(deadline)
            if line is None:
                raise RigError(f"gcode rig {self.url}: no GRBL answered (no banner after a reset)")
            if line.startswith("Grbl"):
                return

    # -- Rig ---------------------------------------------------------------------------------

    def _move(self, xyz: tuple[float, float, float], feed_mm_s: float) -> None:
        x, y, z = xyz
        self.command(f"G1 X{x:.3f} Y{y:.3f} Z{z:.3f} F{feed_mm_s * 60.0:.1f}")

    def _status(self) -> RigStatus:
        self._write(b"?")
        deadline = time.monotonic() + self.timeout_s
        while True:
            line = self._readline(deadline)
            if line is None:
                raise RigError(f"gcode rig {self.url}: no status report within {self.timeout_s:g} s")
            if line.startswith("ALARM:"):
                alarm = self._alarm(line)
                return RigStatus("alarm", (float("nan"),) * 3, str(alarm).split(": ", 1)[1])
            if line.startswith("<") and line.endswith(">"):
                return self._parse_status(line[1:-1])

    def _parse_status(self, body: str) -> RigStatus:
        fields = body.split("|")
        state = _STATES.get(fields[0].split(":")[0].lower(), "hold")
        held_done = fields[0].lower() == "hold:0"
        pos: tuple[float, float, float] | None = None
        machine = False
        for f in fields[1:]:
            key, _, value = f.partition(":")
            if key in ("MPos", "WPos", "WCO"):
                try:
                    xyz = tuple(float(v) for v in value.split(",")[:3])
                except ValueError:
                    raise RigError(f"gcode rig {self.url}: garbled status report <{body}>") from None
                if len(xyz) != 3:
                    raise RigError(f"gcode rig {self.url}: garbled status report <{body}>")
                if key == "WCO":
                    self._wco = (xyz[0], xyz[1], xyz[2])
                else:
                    pos, machine = (xyz[0], xyz[1], xyz[2]), key == "MPos"
        if pos is None:
            raise RigError(f"gcode rig {self.url}: status report without a position <{body}>")
        if machine:
            pos = (pos[0] - self._wco[0], pos[1] - self._wco[1], pos[2] - self._wco[2])
        return RigStatus("idle" if held_done else state, pos)

    def _stop(self) -> None:
        """Feed hold, wait until stopped (position kept), then reset to drop the rest of the move."""
        self._write(b"!")
        deadline = time.monotonic() + 10.0
        while True:
            st = self._status()
            if st.state in ("idle", "alarm"):
                break
            if time.monotonic() > deadline:
                raise RigError(f"gcode rig {self.url}: did not stop within 10 s of a feed hold")
            time.sleep(0.02)
        self._reset()
        if self._status().state == "alarm":
            raise RigError(f"gcode rig {self.url}: alarm after stopping; home it again")
        self.command("G21")
        self.command("G90")

    def _close_internal(self) -> None:
        self._port.close()
