"""The C reference decoder (tools/mcu) against the golden vectors and the Python decoder.

Compiled with gcc -std=c99 -Wall -Wextra -Werror -O2 (plus ASan/UBSan when they work here)
into a temporary directory (gcc is required).
"""

from __future__ import annotations

import os
import random
import struct
import subprocess
import time
from pathlib import Path

import pytest
from fakes.packing import send_message

from optitac_edge.io.protocol import wire
from optitac_edge.io.protocol.decoder import FrameDecoder
from optitac_edge.io.protocol.messages import ContactFlags, ContactMessage, ResultCode, ShapeCode, StatusMessage
from optitac_edge.io.protocol.wire import (
    CSV_HEADER,
    ProtocolError,
    contact_csv_row,
    decode_ack,
    decode_contact,
    decode_status,
    encode_ack,
    encode_command,
    encode_contact,
    encode_frame,
    encode_status,
)

ROOT = Path(__file__).resolve().parents[1]
MCU = ROOT / "tools" / "mcu"
VECTORS = sorted((ROOT / "tests" / "vectors").glob("*.hex"))
CFLAGS = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-O2"]
SAN = ["-fsanitize=address,undefined", "-fno-omit-frame-pointer", "-fno-sanitize-recover=undefined"]
PROGRAMS = {"test_vectors": "test_vectors.c", "optitac_fuzz": "fuzz_main.c", "optitac_rx": "optitac_rx.c"}


def _run(cmd, **kw):
    """subprocess.run without raising on a non-zero exit (the tests check returncode)."""
    return subprocess.run(cmd, check=False, **kw)


def _sanitizers_work(tmp: Path) -> bool:
    src = tmp / "probe.c"
    src.write_text("int main(void) { return 0; }\n")
    try:
        subprocess.run(["gcc", *SAN, str(src), "-o", str(tmp / "probe")], check=True,
                       capture_output=True, timeout=60)
        subprocess.run([str(tmp / "probe")], check=True, capture_output=True, timeout=30)
    except (subprocess.SubprocessError, OSError):
        return False
    return True


@pytest.fixture(scope="module")
def cbin(tmp_path_factory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("mcu")
    flags = CFLAGS + (SAN if _sanitizers_work(tmp) else [])
    out = {}
    for name, src in PROGRAMS.items():
        exe = tmp / name
        r = _run(["gcc", *flags, "-I", str(MCU), str(MCU / src), str(MCU / "optitac_proto.c"),
                            "-o", str(exe)], capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        out[name] = exe
    out["sanitized"] = "-fsanitize=address,undefined" in flags  # type: ignore[assignment]
    return out


def test_c_compiles_also_pedantic(tmp_path):
    r = _run(["gcc", *CFLAGS, "-pedantic", "-Wconversion", "-c", str(MCU / "optitac_proto.c"),
                        "-o", str(tmp_path / "p.o")], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr


def test_c_vectors(cbin):
    r = _run([str(cbin["test_vectors"]), *map(str, VECTORS)], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
    assert r.stdout.strip() == "41 passed, 0 failed"  # 40 vectors + the CRC check value


# -- differential fuzzing --------------------------------------------------------------------

def _random_valid_frame(rng: random.Random) -> bytes:
    kind = rng.randrange(6)
    seq, t_us = rng.randrange(1 << 16), rng.randrange(1 << 32)
    if kind == 0:
        m = ContactMessage(sensor_id=rng.randrange(256), flags=ContactFlags(rng.randrange(32)), t_us=t_us,
                           x_mm=rng.uniform(-400, 400), y_mm=rng.uniform(-400, 400),
                           major_mm=rng.uniform(0, 30), minor_mm=rng.uniform(0, 30),
                           angle_deg=rng.uniform(-90, 90), strength=rng.uniform(0, 300),
                           shape=rng.choice(list(ShapeCode)), confidence=rng.random(),
                           age_us=rng.randrange(100_000))
        return encode_contact(m, seq)
    if kind == 1:
        s = StatusMessage(sensor_id=rng.randrange(256), t_us=t_us, fps_x10=rng.randrange(2000),
                          frames_dropped=rng.randrange(1 << 32), camera_errors=rng.randrange(100),
                          link_errors=rng.randrange(1000), cpu_temp_c_x10=rng.randrange(-400, 1000),
                          calibration_id=rng.randrange(1 << 32), state=rng.randrange(16))
        return encode_status(s, seq)
    if kind == 2:
        return encode_ack(rng.randrange(1 << 16), rng.randrange(5), seq, t_us)
    if kind == 3:
        return encode_command(rng.choice([0x10, 0x11, 0x12, 0x13]), seq, t_us,
                              stream_on=rng.randrange(3), rate_divider=rng.randrange(256),
                              threshold=rng.randrange(6000))
    n = rng.randrange(wire.MAX_PAYLOAD + 1) if kind == 4 else rng.choice([0, 1, 2, 3, 18, 22])
    return encode_frame(rng.randrange(256), seq, t_us, bytes(rng.randrange(256) for _ in range(n)))


def _mutate(rng: random.Random, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(7)
        if not b:
            b.append(rng.randrange(256))
            continue
        i = rng.randrange(len(b))
        if op == 0:
            b[i] ^= 1 << rng.randrange(8)  # bit flip
        elif op == 1:
            b[i] = rng.randrange(256)  # byte replace
        elif op == 2:
            b.insert(i, rng.randrange(256))
        elif op == 3:
            del b[i]
        elif op == 4:
            del b[i:]  # truncate
        elif op == 5:
            b[i] = 0  # a spurious delimiter
        else:
            j = rng.randrange(len(b))
            b[i:i] = b[j:j + rng.randint(1, 8)]  # duplicate a run
    return bytes(b)


def _make_records(seed: int, n: int) -> list[tuple[bytes, set[bytes]]]:
    """(input bytes, the valid frames it was built from) - 40% random, 60% mutated valid frames."""
    rng = random.Random(seed)
    out = []
    for i in range(n):
        r = i % 10
        if r < 2:
            out.append((bytes(rng.randrange(256) for _ in range(rng.randrange(200))), set()))
        elif r < 4:  # COBS-like: rare zeros, short runs, sometimes a frame of another version
            k = rng.randrange(120)
            data = bytes(0 if rng.random() < 0.05 else rng.randrange(1, 256) for _ in range(k))
            if r == 3 and rng.random() < 0.3:
                body = wire.HEADER.pack(rng.choice([0, 2, 255]), rng.randrange(256), 1, 2)
                data += b"\x00" + wire.cobs.encode(body + wire.CRC.pack(wire.crc16(body))) + b"\x00"
            out.append((data, set()))
        else:
            frames = [_random_valid_frame(rng) for _ in range(rng.randint(1, 3))]
            data = b"".join(frames)
            if r != 9:  # 10% stay intact (must all be accepted)
                data = _mutate(rng, data)
            out.append((data, {bytes(cobs_decode_body(f)) for f in frames}))
    return out


def cobs_decode_body(frame: bytes) -> bytes:
    return wire.cobs.decode(frame[:-1])


def _typed(f) -> str:
    dec = {wire.MsgType.CONTACT: decode_contact, wire.MsgType.STATUS: decode_status,
           wire.MsgType.ACK: decode_ack}.get(f.type)
    if dec is None:
        return "-"
    try:
        dec(f.payload)
    except ProtocolError:
        return "0"
    return "1"


def _py_lines(dec: FrameDecoder, data: bytes, prefix: str) -> tuple[list[str], list]:
    frames = dec.feed(data)
    lines = [f"F {prefix}{f.type} {f.seq} {f.t_us} {f.payload.hex() or '-'} {_typed(f)}" for f in frames]
    return lines, frames


def _counters_line(dec: FrameDecoder, prefix: str) -> str:
    c = dec.counters
    return f"C {prefix}{c.frames} {c.cobs} {c.length} {c.crc} {c.version} {c.overflow}"


FIGURES: dict[str, object] = {}


def test_c_and_python_decoders_agree_on_10000_inputs(cbin, tmp_path, fuzz_tool):
    records = _make_records(seed=20240611, n=10_000)
    blob = b"".join(struct.pack("<I", len(d)) + d for d, _ in records)
    (tmp_path / "records.bin").write_bytes(blob)
    t0 = time.perf_counter()
    r = _run([str(cbin["optitac_fuzz"]), "-r", str(tmp_path / "records.bin")],
                       capture_output=True, text=True, timeout=300)
    t_c = time.perf_counter() - t0
    assert r.returncode == 0, r.stderr[-2000:]
    t0 = time.perf_counter()
    expected, accepted, mutated_accepted, false_accepts, collisions = [], 0, 0, 0, 0
    totals = dict.fromkeys(("frames", "cobs", "length", "crc", "version", "overflow"), 0)
    for i, (data, originals) in enumerate(records):
        dec = FrameDecoder()
        lines, frames = _py_lines(dec, data, f"{i} ")
        expected += lines
        expected.append(_counters_line(dec, f"{i} "))
        for k in totals:
            totals[k] += getattr(dec.counters, k)
        for f in frames:
            accepted += 1
            body = wire.HEADER.pack(1, f.type, f.seq, f.t_us) + f.payload
            # never a false accept: the CRC genuinely matches (independent CRC) ...
            raw = body + wire.CRC.pack(fuzz_tool.crc16_ccitt_bitwise(body))
            assert raw == body + wire.CRC.pack(wire.crc16(body))
            # ... and, from mutated valid frames, it is one of the originals unless CRC-16 collided
            if originals:
                if raw in originals:
                    mutated_accepted += 1
                else:
                    collisions += 1
            if i % 10 == 9:
                assert raw in originals
        if i % 10 == 9:  # intact streams: every frame accepted, no error
            assert {wire.HEADER.pack(1, f.type, f.seq, f.t_us) + f.payload for f in frames} == {
                o[:-2] for o in originals}
            assert dec.counters.errors == 0
    t_py = time.perf_counter() - t0
    got = r.stdout.splitlines()
    assert len(got) == len(expected)
    for g, e in zip(got, expected, strict=True):
        assert g == e
    false_accepts = collisions
    # a genuine CRC-16 collision of a corrupted frame has odds ~2^-16 per corrupted frame
    assert collisions <= 2
    FIGURES.update(records=len(records), bytes=len(blob), accepted=accepted,
                   accepted_from_mutated=mutated_accepted, crc_collisions=false_accepts,
                   c_seconds=round(t_c, 3), py_seconds=round(t_py, 3), **totals,
                   sanitized=cbin["sanitized"])
    print("differential fuzz:", FIGURES)
    assert totals["cobs"] > 0 and totals["crc"] > 0 and totals["length"] > 0
    assert totals["overflow"] > 0 and totals["version"] > 0 and accepted > 3000


def test_c_and_python_agree_on_one_long_stream(cbin, tmp_path):
    records = _make_records(seed=7, n=3000)
    stream = b"".join(d for d, _ in records)
    (tmp_path / "stream.bin").write_bytes(stream)
    r = _run([str(cbin["optitac_fuzz"]), str(tmp_path / "stream.bin")], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    dec = FrameDecoder()
    lines, _ = _py_lines(dec, stream, "")
    assert r.stdout.splitlines() == lines + [_counters_line(dec, "")]
    # byte-at-a-time feeding in Python gives the same counters
    dec2 = FrameDecoder()
    for b in stream[:20000]:
        dec2.feed(b)
    dec3 = FrameDecoder()
    dec3.feed(stream[:20000])
    assert dec2.counters == dec3.counters


def test_c_fuzz_pure_random_stream_does_not_crash(cbin, tmp_path):
    data = os.urandom(1 << 20)
    r = _run([str(cbin["optitac_fuzz"])], input=data, capture_output=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    dec = FrameDecoder()
    _py_lines(dec, data, "")
    assert r.stdout.decode().splitlines()[-1] == _counters_line(dec, "")


# -- optitac_rx --------------------------------------------------------------------------------

def _contact_stream(n: int, seed: int = 1) -> tuple[bytes, list[str]]:
    rng = random.Random(seed)
    wire_bytes, rows = b"", []
    for i in range(n):
        m = ContactMessage(sensor_id=1, flags=ContactFlags(rng.randrange(32)), t_us=rng.randrange(1 << 32),
                           x_mm=rng.uniform(-20, 20), y_mm=rng.uniform(-20, 20), major_mm=rng.uniform(0, 9),
                           minor_mm=rng.uniform(0, 9), angle_deg=rng.uniform(-90, 90),
                           strength=rng.uniform(0, 200), shape=rng.choice(list(ShapeCode)),
                           confidence=rng.random(), age_us=rng.randrange(70000))
        frame = encode_contact(m, i)
        wire_bytes += frame
        (f,) = FrameDecoder().feed(frame)
        rows.append(contact_csv_row(f))
        if i % 10 == 0:  # interleaved STATUS and garbage
            wire_bytes += encode_status(StatusMessage(t_us=i), 60000 + i) + b"\x55\x66\x00"
    return wire_bytes, rows


def test_optitac_rx_prints_python_rows(cbin):
    data, rows = _contact_stream(200)
    r = _run([str(cbin["optitac_rx"])], input=data, capture_output=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert r.stdout.decode().splitlines() == [CSV_HEADER, *rows]
    summary = dict(kv.split("=") for kv in r.stderr.decode().split())
    assert summary["contact"] == "200" and summary["status"] == "20" and summary["cobs"] == "20"
    # -n stops after N frames, -q drops the header
    r = _run([str(cbin["optitac_rx"]), "-q", "-n", "5", "-"], input=data, capture_output=True,
                       timeout=60)
    assert r.returncode == 0 and r.stdout.decode().splitlines() == rows[:5]


def test_optitac_rx_idle_timeout(cbin):
    rfd, wfd = os.pipe()
    try:
        t0 = time.perf_counter()
        r = _run([str(cbin["optitac_rx"]), "-t", "0.2"], stdin=rfd, capture_output=True,
                           timeout=30)
        assert r.returncode == 3 and time.perf_counter() - t0 < 5
    finally:
        os.close(rfd)
        os.close(wfd)


def test_serial_transport_to_optitac_rx_over_pty(cbin):
    """The end-to-end path: SerialTransport on a pty slave, optitac_rx on the master."""
    from optitac_edge.io.transports.serial import SerialTransport

    master, slave = os.openpty()
    path = os.ttyname(slave)
    proc = subprocess.Popen([str(cbin["optitac_rx"]), "-q", "-n", "50", "-t", "5"], stdin=master,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        rng = random.Random(3)
        msgs = []
        with SerialTransport(path, queue_size=64) as tr:
            for i in range(50):
                m = ContactMessage(sensor_id=0, flags=ContactFlags.CONTACT, t_us=1000 * i,
                                   x_mm=rng.uniform(-9, 9), y_mm=rng.uniform(-9, 9), major_mm=3.0,
                                   minor_mm=2.0, angle_deg=rng.uniform(-90, 90),
                                   strength=rng.uniform(0, 200), shape=ShapeCode.CIRCLE,
                                   confidence=0.5, age_us=1500)
                msgs.append(m)
                send_message(tr, m)
                time.sleep(0.001)
            out, err = proc.communicate(timeout=20)
        assert proc.returncode == 0, err
        rows = out.decode().splitlines()
        assert len(rows) == 50
        for i, (row, m) in enumerate(zip(rows, msgs, strict=True)):
            (f,) = FrameDecoder().feed(encode_contact(m, i))
            assert row == contact_csv_row(f)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        os.close(master)
        os.close(slave)


def test_result_codes_match_header():
    text = (MCU / "optitac_proto.h").read_text()
    for code in ResultCode:
        assert f"#define OPTITAC_R_{code.name} {int(code)}u" in text
    for name, value in (("CONTACT", 1), ("STATUS", 2), ("PING", 0x10), ("TARE", 0x11), ("STREAM", 0x12),
                        ("SET_THRESHOLD", 0x13), ("ACK", 0x7F)):
        assert f"#define OPTITAC_T_{name} 0x{value:02X}u" in text
