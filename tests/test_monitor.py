"""``optitac-edge monitor``: the MCU's view of the link, decoded and counted; the MCU's commands sent."""

from __future__ import annotations

import fcntl
import os
import pty
import select
import struct
import subprocess
import sys
import termios
import tty

import pytest

from optitac_edge.bringup.monitor import LinkTally, SerialMonitor, command_frame, monitor_serial
from optitac_edge.errors import OptiTacError
from optitac_edge.io.protocol.decoder import FrameDecoder
from optitac_edge.io.protocol.messages import CommandType, ContactFlags, ContactMessage, StatusMessage
from optitac_edge.io.protocol.wire import encode_ack, encode_contact, encode_status, parse_command


def test_counts_rates_gaps_and_errors_from_the_wire() -> None:
    mon = SerialMonitor()
    msg = ContactMessage(sensor_id=0, flags=ContactFlags.CONTACT, t_us=5, x_mm=1.5, y_mm=-2.25, major_mm=4.0,
                         minor_mm=3.0, angle_deg=30.0, strength=12.0)
    stream = b"\x00".join([encode_contact(msg, 1), encode_contact(msg, 2), encode_contact(msg, 5),  # 3, 4 lost
                           encode_status(StatusMessage(sensor_id=0, fps_x10=600), 6), encode_ack(7, 0, 7, 0)])
    bad = bytearray(encode_contact(msg, 8))
    bad[5] ^= 0x40  # a flipped bit: CRC
    lines = mon.feed(b"\x00" + stream + b"\x00" + bytes(bad) + b"\x00", now_ns=0)
    assert lines[0] == "#1 CONTACT t=5 us contact at +1.50, -2.25 mm, 4.00 x 3.00 mm, +30.0°, strength 12.0, shape none"
    assert lines[3].startswith("#6 STATUS 60.0 fps") and lines[4] == "#7 ACK of #7: OK"
    t = mon.tally
    assert t.counts == {"CONTACT": 3, "CONTACT2": 0, "STATUS": 1, "ACK": 1, "RELEASE": 0, "MOTION": 0, "other": 0} and (t.gaps, t.lost) == (1, 2)
    assert mon.decoder.counters.crc == 1
    assert "CONTACT    3.0/s" in mon.summary(now_ns=1_000_000_000) and "crc 1" in mon.summary(1)


def test_rates_are_over_the_last_period() -> None:
    t = LinkTally()
    for k in range(120):
        t.add("CONTACT", k, now_ns=k * 8_333_333)
    assert t.report(now_ns=1_000_000_000).startswith("CONTACT  120.0/s")
    t.add("CONTACT", 120, 1_500_000_000)
    assert t.report(now_ns=2_000_000_000).startswith("CONTACT    1.0/s")


@pytest.mark.parametrize("text, kind", [("ping", CommandType.PING), ("tare", CommandType.TARE),
                                        ("stream on 3", CommandType.STREAM), ("stream off", CommandType.STREAM),
                                        ("threshold 0.05", CommandType.SET_THRESHOLD),
                                        ("protocol 2", CommandType.SET_PROTOCOL)])
def test_typed_commands_are_valid_on_the_wire(text, kind) -> None:
    data, _ = command_frame(text, 9)
    (frame,) = FrameDecoder().feed(data + b"\x00")
    cmd = parse_command(frame.type, frame.seq, frame.payload)
    assert cmd.type == kind and cmd.seq == 9
    if text == "stream on 3":
        assert cmd.stream_on and cmd.rate_divider == 3
    if text.startswith("threshold"):
        assert cmd.threshold == 500
    if text.startswith("protocol"):
        assert cmd.version == 2


@pytest.mark.parametrize("text", ["reboot", "stream on 0", "stream maybe", "threshold 7", "threshold x", "protocol 4"])
def test_bad_commands_are_one_line(text, capsys) -> None:
    from optitac_edge.cli import main

    with pytest.raises(OptiTacError):
        command_frame(text, 1)
    assert main(["monitor", "--serial", "/dev/optitac-absent", "--send", text]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "command" in err


class MasterEnd:
    """The master side of a pty as a pyserial-like port (the MCU's end of the link)."""

    def __init__(self, fd: int) -> None:
        self.fd = fd

    @property
    def in_waiting(self) -> int:
        return struct.unpack("i", fcntl.ioctl(self.fd, termios.FIONREAD, b"\0\0\0\0"))[0]

    def read(self, n: int) -> bytes:
        ready, _, _ = select.select([self.fd], [], [], 0.05)
        return os.read(self.fd, n) if ready else b""

    def write(self, data: bytes) -> int:
        return os.write(self.fd, data)

    def close(self) -> None:
        pass


def _monitor_the_service(commands: list[str], duration_s: float, every: bool = False) -> tuple[list[str], object]:
    """The service on a pty, the monitor at the MCU's end sending ``commands``: (its lines, the monitor)."""
    master, slave = pty.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    service = subprocess.Popen([sys.executable, "-m", "optitac_edge.cli", "run", "--serial", path, "--fps", "60",
                                "--duration", "30"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    lines: list[str] = []
    try:
        os.read(master, 65536) if select.select([master], [], [], 15)[0] else None  # the service is up
        mon = monitor_serial(MasterEnd(master), duration_s, commands, lines.append, every=every)
    finally:
        service.terminate()
        service.wait(timeout=10)
        os.close(master)
        os.close(slave)
    return lines, mon


def test_monitoring_the_running_service_and_commanding_it() -> None:
    lines, mon = _monitor_the_service(["stream on 2", "tare", "threshold 0.05"], 2.0)
    assert lines[:3] == ["sent STREAM", "sent TARE", "sent SET_THRESHOLD"]
    acks = [line for line in lines if "ACK of" in line]
    assert all(any(f"ACK of #{k}: OK" in a for a in acks) for k in (1, 2, 3)), acks
    assert mon.tally.counts["CONTACT"] > 10 and mon.decoder.counters.crc == 0
    assert lines[-1].startswith("CONTACT") and "errors: crc 0" in lines[-1]


def test_monitoring_the_can_bus_decodes_and_finds_counter_gaps() -> None:
    import can

    from optitac_edge.bringup.monitor import monitor_can
    from optitac_edge.io.protocol.can_codec import CanCodec

    codec = CanCodec(sensor_id=0)
    msg = ContactMessage(sensor_id=0, flags=ContactFlags.CONTACT, x_mm=1.5, y_mm=-2.0, major_mm=4.0, minor_mm=3.0)
    sender = can.Bus(channel="optitac-monitor-test", interface="virtual")
    listener = can.Bus(channel="optitac-monitor-test", interface="virtual")
    for counter in (0, 1, 3):  # 2 is missing
        a, b = codec.contact_payloads(msg, counter)
        sender.send(can.Message(arbitration_id=codec.ids["CONTACT_A"], data=a, is_extended_id=False))
        sender.send(can.Message(arbitration_id=codec.ids["CONTACT_B"], data=b, is_extended_id=False))
    sender.send(can.Message(arbitration_id=codec.ids["STATUS"], data=codec.status_payload(StatusMessage(), 4),
                            is_extended_id=False))
    sender.shutdown()
    lines: list[str] = []
    mon = monitor_can("optitac-monitor-test", "virtual", 0.5, lines.append, every=True, bus=listener)
    assert mon.tally.counts["CONTACT"] == 3 and mon.tally.counts["STATUS"] == 1
    assert mon.tally.gaps == 2  # CONTACT_A and CONTACT_B each skip counter 2
    assert any(line.startswith("sensor 0 CONTACT_A: X 1.5") for line in lines)
    assert lines[-1].startswith("CONTACT") and "undecodable 0" in lines[-1]


def test_the_mcu_team_can_switch_the_service_to_protocol_v2_from_the_monitor() -> None:
    """monitor could not send SET_PROTOCOL 2, so v2 could not be tried from the host; it now decodes what v2
    sends (CONTACT2 for every contact, RELEASE)."""
    lines, mon = _monitor_the_service(["protocol 2"], 2.5, every=True)
    assert lines[0] == "sent SET_PROTOCOL 2" and any("ACK of #1: OK" in line for line in lines)
    contact2 = [line for line in lines if " CONTACT2 " in line]
    assert contact2 and any(" contact 1 of " in line for line in contact2)
    # the simulated board has no depth model: 'depth 0.00 mm, force 0.00 N' read as measured (issue 38, item 28)
    touching = [line for line in contact2 if "no contact" not in line]
    assert touching and all("depth not calibrated, force not calibrated" in line for line in touching)
    assert mon.decoder.counters.crc == 0 and mon.tally.bad_payloads == 0


def test_the_monitor_speaks_protocol_v3_and_decodes_motion() -> None:
    """monitor refused 'protocol 3' and could not decode MOTION (issue 38, item 27): now each CONTACT2 is
    followed by its MOTION line (velocity, slide, vibration)."""
    lines, mon = _monitor_the_service(["protocol 3"], 2.5, every=True)
    assert lines[0] == "sent SET_PROTOCOL 3" and any("ACK of #1: OK" in line for line in lines)
    motion = [line for line in lines if " MOTION " in line]
    assert motion and any("v (" in line or "v unknown" in line for line in motion)
    assert mon.tally.counts["MOTION"] == len(motion) and mon.tally.bad_payloads == 0


def test_the_summary_names_contact2_as_contact2() -> None:
    """Issue 52 §6: on protocol v2 the summary labelled CONTACT2 messages as CONTACT."""
    from optitac_edge.bringup.monitor import LinkTally

    t = LinkTally()
    for seq in range(4):
        t.add("CONTACT2", seq, seq * 10**9)
    line = t.report(4 * 10**9)
    assert line.startswith("CONTACT2 ") and "totals: 4 CONTACT2," in line and "CONTACT " not in line
    t = LinkTally()
    t.add("CONTACT", 0, 0)
    assert t.report(10**9).startswith("CONTACT ")
