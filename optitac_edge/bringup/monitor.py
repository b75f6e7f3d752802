"""``optitac-edge monitor``: what the MCU receives, decoded, and the MCU's commands sent by hand.

For the team bringing up the MCU side: it sits where the MCU sits (the other
end of the serial link, or on the CAN bus) and shows every CONTACT, STATUS and
ACK, the rates, sequence gaps and CRC/COBS errors. The counting is pure
(:class:`LinkTally` takes decoded frames and ``now_ns``); one loop at the edge
reads the port.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from optitac_edge.errors import OptiTacError, TransportError
from optitac_edge.io.protocol.decoder import FrameDecoder
from optitac_edge.io.protocol.messages import (
    THRESHOLD_LSB,
    CommandType,
    ContactMessage,
    ContactV2Flags,
    ContactV2Message,
    MotionFlags,
    MotionMessage,
    ResultCode,
)
from optitac_edge.io.protocol.wire import (
    THRESHOLD_MAX,
    THRESHOLD_MIN,
    U16,
    Frame,
    MsgType,
    ProtocolError,
    decode_ack,
    decode_contact,
    decode_status,
    encode_command,
)
from optitac_edge.io.protocol.wire_v2 import decode_contact2, decode_motion, decode_release

#: Commands the monitor sends, as typed: ``ping``, ``tare``, ``stream on [DIVIDER]``, ``stream off``,
#: ``threshold LEVEL`` (relative units, 0.001..0.5), ``protocol 1|2|3`` (SET_PROTOCOL).
COMMAND_HELP = "ping | tare | stream on [DIVIDER] | stream off | threshold LEVEL (0.001..0.5) | protocol 1|2|3"


def command_frame(text: str, seq: int) -> tuple[bytes, str]:
    """The wire frame of a typed command and its name.

    Raises
    ------
    OptiTacError
        One line for anything else.
    """
    words = text.lower().split()
    if words in (["ping"], ["tare"]):
        kind = CommandType.PING if words[0] == "ping" else CommandType.TARE
        return encode_command(kind, seq), words[0].upper()
    if words[:1] == ["stream"] and len(words) in (2, 3) and words[1] in ("on", "off"):
        try:
            divider = int(words[2]) if len(words) == 3 else 1
        except ValueError:
            divider = 0
        if not 1 <= divider <= 255 or (words[1] == "off" and len(words) == 3):
            raise OptiTacError(f"command {text!r}: stream on takes a divider 1..255")
        return encode_command(CommandType.STREAM, seq, stream_on=words[1] == "on", rate_divider=divider), "STREAM"
    if words[:1] == ["threshold"] and len(words) == 2:
        try:
            level = round(float(words[1]) / THRESHOLD_LSB)
        except ValueError:
            level = -1
        if not THRESHOLD_MIN <= level <= THRESHOLD_MAX:
            raise OptiTacError(f"command {text!r}: the level must be a number in 0.001..0.5")
        return encode_command(CommandType.SET_THRESHOLD, seq, threshold=level), "SET_THRESHOLD"
    if words[:1] == ["protocol"] and len(words) == 2:
        if words[1] not in ("1", "2", "3"):
            raise OptiTacError(f"command {text!r}: the protocol version is 1, 2 or 3")
        return encode_command(CommandType.SET_PROTOCOL, seq, version=int(words[1])), f"SET_PROTOCOL {words[1]}"
    raise OptiTacError(f"unknown command {text!r} (commands: {COMMAND_HELP})")


@dataclass
class LinkTally:
    """Counts of what arrived, rates over the last report period, sequence gaps; pure (no I/O, no clock)."""

    counts: dict[str, int] = field(default_factory=lambda: {"CONTACT": 0, "CONTACT2": 0, "STATUS": 0, "ACK": 0,
                                                            "RELEASE": 0, "MOTION": 0, "other": 0})
    gaps: int = 0
    lost: int = 0
    bad_payloads: int = 0
    last_seq: int | None = None
    last_contact: str = ""
    last_status: str = ""
    acks: list[str] = field(default_factory=list)
    _period: dict[str, int] = field(default_factory=dict)
    _since_ns: int | None = None

    def add(self, name: str, seq: int | None, now_ns: int) -> None:
        """Count one message; ``seq`` (16-bit, None when the link has none) finds gaps."""
        if self._since_ns is None:
            self._since_ns = now_ns
        self.counts[name] = self.counts.get(name, 0) + 1
        self._period[name] = self._period.get(name, 0) + 1
        if seq is not None:
            if self.last_seq is not None:
                step = (seq - self.last_seq) & U16
                if step != 1:
                    self.gaps += 1
                    self.lost += (step - 1) if step else 0
            self.last_seq = seq

    def report(self, now_ns: int) -> str:
        """One line: rates since the last report, totals, gaps; the period starts again."""
        span = (now_ns - self._since_ns) / 1e9 if self._since_ns is not None else 0.0
        rate = (lambda n: n / span if span > 0 else 0.0)
        kind = "CONTACT2" if self.counts["CONTACT2"] > self.counts["CONTACT"] else "CONTACT"  # v2/v3: CONTACT2
        line = (f"{kind} {rate(self._period.get(kind, 0)):6.1f}/s  STATUS {rate(self._period.get('STATUS', 0)):4.1f}/s"
                f"  totals: {self.counts[kind]} {kind}, {self.counts['STATUS']} STATUS, {self.counts['ACK']} ACK"
                f"  gaps {self.gaps} ({self.lost} missing)")
        self._period.clear()
        self._since_ns = now_ns
        return line


def _contact_text(msg: ContactMessage) -> str:
    if not msg.flags & 1:
        return "no contact"
    return (f"contact at {msg.x_mm:+.2f}, {msg.y_mm:+.2f} mm, {msg.major_mm:.2f} x {msg.minor_mm:.2f} mm, "
            f"{msg.angle_deg:+.1f}°, strength {msg.strength:.1f}, shape {msg.shape.name.lower()}")


def _contact2_text(msg: ContactV2Message) -> str:
    if not msg.n_contacts:
        return f"sensor {msg.sensor_id}: no contact"
    flags = ContactV2Flags(msg.flags)  # depth and force only where calibrated (else sent as 0)
    depth = f"depth {msg.depth_mm:.2f} mm" if flags & ContactV2Flags.DEPTH else "depth not calibrated"
    force = f"force {msg.force_n:.2f} N" if flags & ContactV2Flags.FORCE else "force not calibrated"
    touch = ", touch" if flags & ContactV2Flags.TOUCH else ""
    return (f"sensor {msg.sensor_id} contact {msg.index + 1} of {msg.n_contacts} (id {msg.contact_id}{touch}) at "
            f"{msg.x_mm:+.2f}, {msg.y_mm:+.2f} mm, {msg.major_mm:.2f} x {msg.minor_mm:.2f} mm, {msg.angle_deg:+.1f}°, "
            f"strength {msg.strength:.1f}, {depth}, {force}")


class SerialMonitor:
    """Decodes a serial link as the MCU would (:class:`FrameDecoder`) and tallies what arrives."""

    def __init__(self) -> None:
        self.decoder = FrameDecoder()
        self.tally = LinkTally()

    def feed(self, data: bytes, now_ns: int) -> list[str]:
        """Bytes from the link; returns a line per message."""
        lines = []
        for frame in self.decoder.feed(data):
            lines.append(self._frame(frame, now_ns))
        return lines

    def _frame(self, frame: Frame, now_ns: int) -> str:
        t = self.tally
        try:
            if frame.type == MsgType.CONTACT:
                msg = decode_contact(frame.payload, frame.t_us)
                t.add("CONTACT", frame.seq, now_ns)
                t.last_contact = _contact_text(msg)
                return f"#{frame.seq} CONTACT t={frame.t_us} us {t.last_contact}"
            if frame.type == MsgType.STATUS:
                st = decode_status(frame.payload, frame.t_us)
                t.add("STATUS", frame.seq, now_ns)
                t.last_status = (f"{st.fps_x10 / 10:.1f} fps, state {st.state:#04x}, dropped {st.frames_dropped}, "
                                 f"camera errors {st.camera_errors}, link errors {st.link_errors}, "
                                 f"calibration {st.calibration_id:08x}")
                return f"#{frame.seq} STATUS {t.last_status}"
            if frame.type == MsgType.CONTACT2:  # protocol v2: one for each contact of the frame (counted apart)
                c2 = decode_contact2(frame.payload, frame.t_us)
                t.add("CONTACT2", frame.seq, now_ns)
                t.last_contact = _contact2_text(c2)
                return f"#{frame.seq} CONTACT2 t={frame.t_us} us frame {c2.frame} {t.last_contact}"
            if frame.type == MsgType.MOTION:  # protocol v3: after each CONTACT2, its contact's motion
                mo = decode_motion(frame.payload, frame.t_us)
                t.add("MOTION", frame.seq, now_ns)
                return f"#{frame.seq} MOTION frame {mo.frame} {_motion_text(mo)}"
            if frame.type == MsgType.RELEASE:
                rel = decode_release(frame.payload, frame.t_us)
                t.add("RELEASE", frame.seq, now_ns)
                return (f"#{frame.seq} RELEASE of contact {rel.contact_id} (sensor {rel.sensor_id}, touched in frame "
                        f"{rel.touch_frame}) at frame {rel.frame}")
            if frame.type == MsgType.ACK:
                ack = decode_ack(frame.payload)
                t.add("ACK", frame.seq, now_ns)
                try:
                    result = ResultCode(ack.result).name
                except ValueError:
                    result = str(ack.result)
                t.acks.append(f"ACK of #{ack.seq_acked}: {result}")
                return f"#{frame.seq} {t.acks[-1]}"
        except ProtocolError as exc:
            t.bad_payloads += 1
            return f"#{frame.seq} bad payload ({exc})"
        t.add("other", frame.seq, now_ns)
        return f"#{frame.seq} message type {frame.type:#04x}"

    def summary(self, now_ns: int) -> str:
        c = self.decoder.counters
        return (f"{self.tally.report(now_ns)}  errors: crc {c.crc}, cobs {c.cobs}, length {c.length}, "
                f"version {c.version}, overflow {c.overflow}, payload {self.tally.bad_payloads}")


def _motion_text(mo: MotionMessage) -> str:
    """A MOTION message in a line: the contact's velocity and slide, the frame's vibration, as its flags say."""
    f = MotionFlags(mo.flags)
    parts = [f"contact {mo.contact_id}" if mo.contact_id else "no contact"]
    parts.append(f"v ({mo.vx_mm_s:.1f}, {mo.vy_mm_s:.1f}) mm/s" if f & MotionFlags.VELOCITY else "v unknown")
    if f & MotionFlags.SLIDING:
        parts.append(f"sliding since frame {mo.slide_frame}" + (" (began)" if f & MotionFlags.SLIDE_BEGAN else ""))
    if f & MotionFlags.VIBRATION:
        parts.append(f"vibration {mo.vibration:.1f}" + (" (vibrating)" if f & MotionFlags.VIBRATING else ""))
    return ", ".join(parts)


def open_monitor_port(port: str, baudrate: int) -> Any:
    """The MCU's end of the serial link, for :func:`monitor_serial` (refused while another process holds it).

    Raises
    ------
    TransportError
        When the port cannot be opened (or is held by another process).
    """
    import serial

    try:
        return serial.serial_for_url(port, baudrate=baudrate, timeout=0.05, exclusive=True)
    except (serial.SerialException, ValueError, OSError) as exc:
        raise TransportError(f"monitor: cannot open {port} ({exc})") from None


def monitor_serial(serial_port: Any, duration_s: float | None, commands: list[str], say: Callable[[str], None],
                   every: bool = False, period_s: float = 1.0, stop: threading.Event | None = None) -> SerialMonitor:
    """Read the serial link ``serial_port`` (:func:`open_monitor_port`; closed at the end) until ``duration_s``
    (or ``stop``), printing a summary every ``period_s``.

    ``commands`` (typed as :data:`COMMAND_HELP`) are sent at the start; ``every`` prints each message.
    """
    frames = [command_frame(text, seq) for seq, text in enumerate(commands, start=1)]
    mon = SerialMonitor()

    def poll() -> list[str]:
        chunk = serial_port.read(max(1, serial_port.in_waiting))
        return [line for line in mon.feed(chunk, time.monotonic_ns())
                if every or " ACK " in line or "bad payload" in line]

    try:
        for data, name in frames:
            serial_port.write(b"\x00" + data)
            say(f"sent {name}")
        _watch(poll, mon.summary, say, duration_s, period_s, stop)
    finally:
        serial_port.close()
    say(mon.summary(time.monotonic_ns()))
    return mon


def _watch(poll: Callable[[], list[str]], summary: Callable[[int], str], say: Callable[[str], None],
           duration_s: float | None, period_s: float, stop: threading.Event | None) -> None:
    """Call ``poll`` until ``duration_s`` passes or ``stop`` is set, saying the lines it returns and
    ``summary(now_ns)`` every ``period_s``."""
    stop = stop or threading.Event()
    start = time.monotonic_ns()
    next_report = start + int(period_s * 1e9)
    while not stop.is_set():
        if duration_s is not None and time.monotonic_ns() - start >= duration_s * 1e9:
            break
        for line in poll():
            say(line)
        now = time.monotonic_ns()
        if now >= next_report:
            next_report = now + int(period_s * 1e9)
            say(summary(now))


class CanMonitor:
    """Decodes the sensor's CAN frames with the packaged database; COUNTER gaps per message."""

    def __init__(self, dbc_path: str | None = None) -> None:
        self.dbc_path = dbc_path
        self.tally = LinkTally()
        self.counters: dict[tuple[int, str], int] = {}
        self.undecodable = 0

    def feed(self, arbitration_id: int, data: bytes, now_ns: int) -> str | None:
        from optitac_edge.io.protocol.can_codec import COUNTER_MODULO, decode_frame

        try:
            decoded = decode_frame(arbitration_id, data, dbc_path=self.dbc_path)
        except Exception as exc:  # noqa: BLE001 - cantools raises assorted errors on bad frames
            self.undecodable += 1
            return f"id {arbitration_id:#05x}: not decodable ({type(exc).__name__})"
        if decoded is None:
            return None
        sensor, name, signals = decoded
        counter = int(signals.get("COUNTER", 0))
        key = (sensor, name)
        if key in self.counters and (counter - self.counters[key]) % COUNTER_MODULO != 1:
            self.tally.gaps += 1
        self.counters[key] = counter
        kind = "STATUS" if name == "STATUS" else "CONTACT" if name == "CONTACT_A" else "other"
        self.tally.add(kind, None, now_ns)
        shown = ", ".join(f"{k} {v:g}" if isinstance(v, (int, float)) and math.isfinite(v) else f"{k} {v}"
                          for k, v in signals.items())
        return f"sensor {sensor} {name}: {shown}"

    def summary(self, now_ns: int) -> str:
        return f"{self.tally.report(now_ns)}  undecodable {self.undecodable}"


def monitor_can(channel: str, interface: str, duration_s: float | None, say: Callable[[str], None],
                every: bool = False, period_s: float = 1.0, stop: threading.Event | None = None,
                bus: Any = None) -> CanMonitor:
    """Read the CAN bus until ``duration_s`` (or ``stop``); protocol v1 has no commands on CAN."""
    if bus is None:
        import can

        try:
            bus = can.Bus(channel=channel, interface=interface)
        except (can.CanError, OSError, ValueError) as exc:
            raise TransportError(f"monitor: cannot open CAN {interface} channel {channel!r} ({exc})") from None
    mon = CanMonitor()

    def poll() -> list[str]:
        msg = bus.recv(0.05)
        if msg is None:
            return []
        line = mon.feed(msg.arbitration_id, bytes(msg.data), time.monotonic_ns())
        return [line] if line is not None and (every or "not decodable" in line) else []

    try:
        _watch(poll, mon.summary, say, duration_s, period_s, stop)
    finally:
        bus.shutdown()
    say(mon.summary(time.monotonic_ns()))
    return mon
