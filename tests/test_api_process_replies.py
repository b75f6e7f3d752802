"""Every request gets its own reply (issue 52 §2): numbered calls, answers matched to them, interrupted calls,
two threads, oversized and deeply nested messages, and a parent that dies while its child opens.

Before: after a call interrupted by SIGINT the next ``status()`` returned a Reading; two threads on one
SensorProcess got each other's answers (30 of 80); a 2^62-byte length header was a MemoryError.
"""

from __future__ import annotations

import json
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import optitac_edge as ot
from optitac_edge.api import sensor_messages as messages
from optitac_edge.api.sensor_process import SensorProcess, _serve_call
from optitac_edge.errors import OptiTacError

STATUS = ot.Status(0, "main", 10, 4, 1, True, "abc", True, 240.0, 3, 7)
READING = ot.Reading(0, 12, 5, (), (), 1.0, True, True, False)


class _Child:
    """The test plays the child on the other end of the socket pair."""

    def __init__(self) -> None:
        mine, theirs = socket.socketpair()
        self.conn = Connection(theirs.detach())
        self.parent_conn = Connection(mine.detach())

    def call(self) -> dict:
        return messages.decode(self.conn.recv_bytes())

    def answer(self, value, number: int) -> None:
        messages.send_answer(self.conn, value, number)


class _Process:
    """A stand-in for the child's Popen: already ended."""

    pid = 0
    returncode = 0

    def poll(self):
        return 0

    def wait(self, timeout=None):
        return 0

    def kill(self):
        pass


def _parent(child: _Child) -> SensorProcess:
    return SensorProcess(_Process(), child.parent_conn, 0, "main", 0.5)


def test_the_answer_to_an_interrupted_call_is_not_the_next_calls(monkeypatch):
    child = _Child()
    sp = _parent(child)
    real_poll = Connection.poll
    calls = {"n": 0}

    def interrupted_once(self, timeout=0.0):
        calls["n"] += 1
        if calls["n"] == 1:
            raise KeyboardInterrupt  # a Ctrl-C the program catches, while read() waited
        return real_poll(self, timeout)

    monkeypatch.setattr(Connection, "poll", interrupted_once)
    with pytest.raises(KeyboardInterrupt):
        sp.read(1.0)
    first = child.call()
    assert first["call"] == "read" and first["id"] == 1
    child.answer(READING, 1)  # the interrupted read's answer comes late
    t = threading.Thread(target=lambda: (child.call(), child.answer(STATUS, 2)))
    t.start()
    assert sp.status() == STATUS  # not the Reading
    t.join()


def test_an_answer_numbered_beyond_the_call_ends_the_connection_in_one_line():
    child = _Child()
    sp = _parent(child)
    t = threading.Thread(target=lambda: (child.call(), child.answer(STATUS, 9)))
    t.start()
    with pytest.raises(messages.MalformedMessage, match="an answer to call 9, the last call was 1"):
        sp.status()
    t.join()
    with pytest.raises(OptiTacError, match="is closed"):
        sp.status()


def test_a_length_header_of_2_62_bytes_is_one_line_not_memory_error():
    child = _Child()
    sp = _parent(child)

    def huge():
        child.call()
        child.conn._send(b"\xff\xff\xff\xff" + struct.pack("!Q", 2**62))  # multiprocessing's long-message header

    t = threading.Thread(target=huge)
    t.start()
    with pytest.raises(messages.MalformedMessage, match="longer than"):
        sp.status()
    t.join()


def test_the_child_refuses_a_huge_or_deep_call_and_ends_without_a_traceback():
    for raw in (b"\xff\xff\xff\xff" + struct.pack("!Q", 2**62), None):
        child = _Child()
        if raw is None:
            child.parent_conn.send_bytes(b'{"call": "status", "args": ' + b"[" * 100000 + b"]" * 100000 + b"}")
        else:
            child.parent_conn._send(raw)
        assert _serve_call(child.conn, None) is False  # ended: the stream cannot be trusted
        if raw is None:
            header = json.loads(child.parent_conn.recv_bytes())
            assert header["kind"] == "error" and "nested too deeply" in header["message"]


def test_deeply_nested_arguments_are_one_line():
    child = _Child()
    sp = _parent(child)
    deep: list = []
    for _ in range(100000):
        deep = [deep]
    with pytest.raises(OptiTacError, match=r"read\(\): its arguments cannot be sent"):
        sp.read(deep)
    assert not child.conn.poll(0.0)  # nothing was sent


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=200) | st.builds(lambda d: json.dumps(d).encode(), st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.sampled_from(["kind", "id", "fields", "value",
                                                                                  "arrays", "x"]), inner, max_size=4),
    max_leaves=20)))
def test_generated_answers_are_a_value_or_one_malformed_line(raw):
    """Generated answer bytes: a value of a documented kind, or a MalformedMessage; never another exception."""
    a, b = socket.socketpair()
    ca, cb = Connection(a.detach()), Connection(b.detach())
    try:
        ca.send_bytes(raw)
        try:
            number, _ = messages.recv_reply(cb)
        except messages.MalformedMessage as exc:
            assert "\n" not in str(exc)
        except EOFError:
            pass  # a reading whose arrays never come: the other side closed (below, never here)
        else:
            assert isinstance(number, int) and number >= 0
    except BlockingIOError:
        pass
    finally:
        ca.close()
        cb.close()


@pytest.fixture(scope="module")
def slow_sim():
    """A simulated sensor at 20 frames/s: a read() waits ~50 ms for its frame."""
    with ot.open_sensor_process("sim", settings={"camera.fps": 20}) as sp:
        yield sp


def test_a_real_child_after_a_caught_sigint_answers_each_call_its_own(slow_sim):
    sp = slow_sim

    def interrupt(*_):
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGALRM, interrupt)
    try:
        for delay in (0.01, 0.03, 0.07):
            signal.setitimer(signal.ITIMER_REAL, delay)
            try:
                sp.tare(3.0)
                time.sleep(0.2)
            except KeyboardInterrupt:
                pass
            signal.setitimer(signal.ITIMER_REAL, 0)
            if sp._closed:  # interrupted half across a message: ended, and said so
                with pytest.raises(OptiTacError, match="interrupted while"):
                    sp.status()
                return
            assert isinstance(sp.status(), ot.Status)
            assert isinstance(sp.read(2.0), ot.Reading)
            assert isinstance(sp.status(), ot.Status)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def test_two_threads_on_one_child_each_get_their_own_answers(slow_sim):
    sp = slow_sim
    wrong: list[str] = []

    def calls(kind):
        for _ in range(20):
            got = sp.status() if kind == "status" else sp.read(2.0)
            want = ot.Status if kind == "status" else ot.Reading
            if not isinstance(got, want):
                wrong.append(f"{kind}: {type(got).__name__}")

    threads = [threading.Thread(target=calls, args=(k,)) for k in ("status", "read")]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert wrong == []


PARENT = r"""
import subprocess, sys
from optitac_edge.api import sensor_process
real = subprocess.Popen
class Shown(real):
    def __init__(self, *a, **k):
        super().__init__(*a, **k)
        print(self.pid, flush=True)
sensor_process.subprocess.Popen = Shown
sensor_process.open_sensor_process("sim", settings={"camera.fps": 5, "calibration.rest_frames": 200})
"""


def test_a_child_whose_parent_dies_while_it_opens_ends_at_once():
    parent = subprocess.Popen([sys.executable, "-c", PARENT], stdout=subprocess.PIPE, text=True)
    child = int(parent.stdout.readline())
    time.sleep(1.0)  # the child is opening: 200 rest frames at 5 frames/s take 40 s
    parent.kill()
    parent.wait()
    ended = None
    for _ in range(100):  # the watch polls every 0.1 s
        try:
            with open(f"/proc/{child}/stat") as f:
                if f.read().split(")")[-1].split()[0] == "Z":
                    ended = True
                    break
        except FileNotFoundError:
            ended = True
            break
        time.sleep(0.1)
    assert ended, "the child went on opening for its dead parent"
