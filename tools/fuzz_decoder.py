#!/usr/bin/env python3
"""Fuzz the MCU-input path: the COBS/CRC frame decoder and the command parser.

Feeds N inputs (half random byte strings, half mutated valid frames: bit flips,
byte replacements, insertions, deletions, truncations, splices, stray
delimiters) into :class:`~optitac_edge.io.protocol.FrameDecoder` in random chunks
and checks against an independent oracle written from docs/protocol.md:

* no exception escapes the decoder or :func:`parse_command`;
* every accepted frame is exactly what the oracle accepts (COBS valid, >= 10
  bytes, CRC-16 matches, version 1, <= 64 encoded bytes), none other;
* the decoder's counters equal the oracle's counts, reason by reason;
* every command the parser accepts has its values in range; every other one
  gets a non-zero result code.

Usage: python tools/fuzz_decoder.py [N] [SEED]   (default 1,000,000 inputs, seed 0)
"""

from __future__ import annotations

import struct
import sys
import time
from collections import Counter

import numpy as np
from cobs import cobs

from optitac_edge.io.protocol.decoder import FrameDecoder
from optitac_edge.io.protocol.messages import Command, CommandType, ResultCode
from optitac_edge.io.protocol.wire import encode_command, encode_frame, parse_command


def crc16_ccitt_bitwise(data: bytes) -> int:
    """CRC-16/CCITT-FALSE written out bit by bit (independent of wire.crc16; also the C tests' oracle)."""
    crc = 0xFFFF
    for b in data:
        crc ^= b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) & 0xFFFF if crc & 0x8000 else (crc << 1) & 0xFFFF
    return crc


def oracle(segment: bytes) -> tuple[str, tuple | None]:
    """What one delimited, non-empty segment must give: ('frames', (type, seq, t_us, payload)) or a reason."""
    if len(segment) > 64:
        return "overflow", None
    try:
        raw = cobs.decode(segment)
    except cobs.DecodeError:
        return "cobs", None
    if len(raw) < 10:
        return "length", None
    body, (crc,) = raw[:-2], struct.unpack("<H", raw[-2:])
    if crc16_ccitt_bitwise(body) != crc:
        return "crc", None
    version, msg_type, seq, t_us = struct.unpack_from("<BBHI", body)
    if version != 1:
        return "version", None
    return "frames", (msg_type, seq, t_us, body[8:])


def _valid_frames(rng: np.random.Generator) -> bytes:
    kind = int(rng.integers(6))
    seq, t_us = int(rng.integers(1 << 16)), int(rng.integers(1 << 32))
    if kind < 4:
        ctype = (CommandType.PING, CommandType.TARE, CommandType.STREAM, CommandType.SET_THRESHOLD)[kind]
        return encode_command(ctype, seq, t_us, stream_on=bool(rng.integers(2)),
                              rate_divider=int(rng.integers(0, 300)), threshold=int(rng.integers(0, 6000)))
    n = int(rng.integers(0, 54))
    return encode_frame(int(rng.integers(256)), seq, t_us, rng.bytes(n))


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        op = int(rng.integers(8))
        i = int(rng.integers(len(b))) if b else 0
        if op == 0 and b:
            b[i] ^= 1 << int(rng.integers(8))
        elif op == 1 and b:
            b[i] = int(rng.integers(256))
        elif op == 2:
            b.insert(i, int(rng.integers(256)))
        elif op == 3 and b:
            del b[i]
        elif op == 4:
            b = b[:i]
        elif op == 5:
            b.insert(i, 0)
        elif op == 6:
            b += _valid_frames(rng)
        elif op == 7 and b:
            b[i:i] = b[: int(rng.integers(1, 20))]
    return bytes(b)


def run(n: int, seed: int = 0) -> dict[str, int]:
    rng = np.random.default_rng(seed)
    dec = FrameDecoder()
    expected = Counter()
    results = Counter()
    for k in range(n):
        if k % 2:
            data = rng.bytes(int(rng.integers(0, 100)))
            if rng.random() < 0.5:  # random bytes with delimiters sprinkled in
                arr = np.frombuffer(data, np.uint8).copy()
                arr[rng.random(arr.size) < 0.05] = 0
                data = arr.tobytes()
        else:
            data = mutate(_valid_frames(rng), rng)
        data += b"\x00"
        # the oracle's view: segments between delimiters (the decoder starts each input clean)
        want = []
        for seg in data.split(b"\x00")[:-1]:
            if seg:
                reason, frame = oracle(seg)
                expected[reason] += 1
                if frame is not None:
                    want.append(frame)
        # the decoder, fed in random chunks
        got = []
        cuts = sorted({int(c) for c in rng.integers(0, len(data) + 1, int(rng.integers(0, 4)))})
        prev = 0
        for c in [*cuts, len(data)]:
            got += dec.feed(data[prev:c])
            prev = c
        got_t = [(f.type, f.seq, f.t_us, bytes(f.payload)) for f in got]
        if got_t != want:
            raise AssertionError(f"input {k} ({data.hex()}): decoder {got_t} != oracle {want}")
        for msg_type, seq, _t, payload in got_t:
            parsed = parse_command(msg_type, seq, payload)
            if isinstance(parsed, Command):
                results["accepted"] += 1
                if parsed.type == CommandType.STREAM:
                    assert 1 <= parsed.rate_divider <= 255, parsed
                if parsed.type == CommandType.SET_THRESHOLD:
                    assert 10 <= parsed.threshold <= 5000, parsed
            else:
                assert parsed[0] == seq and parsed[1] != ResultCode.OK, parsed
                results[ResultCode(parsed[1]).name] += 1
    counters = dec.counters.as_dict()
    if counters != {k: expected[k] for k in counters}:
        raise AssertionError(f"decoder counters {counters} != oracle {dict(expected)}")
    return {"inputs": n, **counters, **{f"cmd_{k}": v for k, v in results.items()}}


def main(argv: list[str]) -> int:
    n = int(argv[1]) if len(argv) > 1 else 1_000_000
    seed = int(argv[2]) if len(argv) > 2 else 0
    t0 = time.perf_counter()
    out = run(n, seed)
    print(" ".join(f"{k}={v}" for k, v in out.items()), f"seconds={time.perf_counter() - t0:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
