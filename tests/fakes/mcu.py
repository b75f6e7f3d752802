"""The MCU end of a serial line (a pty pair), as the tests drive it."""

from __future__ import annotations

import os
import select
import time

from optitac_edge.io.protocol.decoder import FrameDecoder


def wait_for(cond, timeout=3.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.005)
    return cond()


class FakeMcu:
    """The MCU end of a pty pair: writes commands, reads and decodes what the sensor sends."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        self.path = os.ttyname(self.slave)
        self.decoder = FrameDecoder()
        self.frames: list = []

    def write(self, data: bytes) -> None:
        os.write(self.master, data)

    def read_until(self, cond, timeout=3.0) -> list:
        deadline = time.monotonic() + timeout
        while not cond(self.frames) and time.monotonic() < deadline:
            r, _, _ = select.select([self.master], [], [], 0.02)
            if r:
                self.frames += self.decoder.feed(os.read(self.master, 4096))
        return self.frames

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass
