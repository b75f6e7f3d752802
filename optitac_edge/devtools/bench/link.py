"""The end-to-end reader: a separate process reading CONTACT frames from a pty, timestamped at their last byte."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import tty
from pathlib import Path

import numpy as np


def reader_main(fd: int, seconds: float, out_path: str, started_ns: int) -> None:
    """The separate process: read CONTACT frames from the pty, timestamp each at its last byte."""
    from optitac_edge.io.protocol.decoder import FrameDecoder
    from optitac_edge.io.protocol.wire import MsgType, decode_contact

    dec = FrameDecoder()
    rows: list[tuple[int, int, int, int]] = []  # (seq, t_us, received ns, age at fill µs)
    first_ns = None
    seqs: list[int] = []  # every frame's (CONTACT, STATUS) sequence number
    end = time.monotonic() + seconds
    os.set_blocking(fd, True)
    import select

    while time.monotonic() < end:
        r, _, _ = select.select([fd], [], [], 0.2)
        if not r:
            continue
        try:
            data = os.read(fd, 65536)
        except OSError:
            break
        now = time.monotonic_ns()
        for fr in dec.feed(data):
            seqs.append(fr.seq)
            if first_ns is None:
                first_ns = now
            if fr.type == MsgType.CONTACT:
                try:
                    age_us = decode_contact(fr.payload).age_us
                except ValueError:
                    age_us = -1
                rows.append((fr.seq, fr.t_us, now, age_us))
    Path(out_path).write_text(json.dumps({"rows": rows, "seqs": seqs, "first_ns": first_ns,
                                          "started_ns": started_ns,
                                          "decode_errors": dec.counters.__dict__}))


def start_reader(master: int, seconds: float, out_path: str) -> subprocess.Popen:
    code = ("import sys; from optitac_edge.devtools.bench.link import reader_main; "
            "reader_main(int(sys.argv[1]), float(sys.argv[2]), sys.argv[3], int(sys.argv[4]))")
    return subprocess.Popen([sys.executable, "-c", code, str(master), str(seconds), out_path,
                             str(time.monotonic_ns())], pass_fds=(master,))


def open_pty() -> tuple[int, int, str]:
    master, slave = os.openpty()
    tty.setraw(slave)  # no newline translation: the link is binary
    return master, slave, os.ttyname(slave)


def latencies(rows: list[list[int]], seqs: list[int]) -> tuple[np.ndarray, int]:
    """Latency (ns) of each CONTACT packet, and the frames missing from the sequence numbers."""
    lat = []
    for _seq, t_us, recv_ns, _age in rows:
        recv_us = recv_ns // 1000
        age_us = (recv_us - t_us) % (1 << 32)  # t_us wraps at 32 bits
        lat.append(age_us * 1000 + recv_ns % 1000)
    gaps = np.mod(np.diff(np.asarray(seqs, dtype=np.int64)), 1 << 16)
    missing = int(np.sum(gaps[gaps > 1] - 1)) if gaps.size else 0
    return np.asarray(lat, dtype=np.float64), missing
