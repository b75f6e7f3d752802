"""sd_notify over a real unix datagram socket; no-ops and never raising."""

from __future__ import annotations

import os
import socket
import uuid

import pytest

from optitac_edge.io.sdnotify import Notifier, watchdog_period


@pytest.fixture
def listener(tmp_path):
    path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(2.0)
    yield str(path), sock
    sock.close()


def test_notify_to_path_socket(listener):
    path, sock = listener
    assert Notifier(env={"NOTIFY_SOCKET": path}).send("READY=1")
    assert sock.recv(1024) == b"READY=1"


def test_notify_abstract_namespace():
    name = f"optitac-test-{uuid.uuid4().hex}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(b"\0" + name.encode())
    sock.settimeout(2.0)
    try:
        assert Notifier(env={"NOTIFY_SOCKET": "@" + name}).send("WATCHDOG=1")
        assert sock.recv(1024) == b"WATCHDOG=1"
    finally:
        sock.close()


def test_notify_without_socket_is_a_noop(monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    assert Notifier().send("READY=1") is False
    assert Notifier(env={"NOTIFY_SOCKET": ""}).send("READY=1") is False
    assert Notifier(env={"NOTIFY_SOCKET": "vsock:2:1234"}).send("READY=1") is False


def test_notify_never_raises(tmp_path):
    for env in ({"NOTIFY_SOCKET": str(tmp_path / "absent.sock")}, {"NOTIFY_SOCKET": "/" + "x" * 200}):
        notifier = Notifier(env=env)
        assert notifier.send("READY=1") is False and notifier.failed == 1


def test_watchdog_period():
    assert watchdog_period({}) is None
    assert watchdog_period({"WATCHDOG_USEC": "5000000"}) == 5.0
    assert watchdog_period({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": str(os.getpid())}) == 5.0
    assert watchdog_period({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": "1"}) is None
    assert watchdog_period({"WATCHDOG_USEC": "junk"}) is None
    assert watchdog_period({"WATCHDOG_USEC": "0"}) is None


def test_notifier_ready_status_and_rate_limited_watchdog(listener):
    path, sock = listener
    sd = Notifier(env={"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "4000000"})
    assert sd.enabled and sd.watchdog_interval_s == 1.0
    assert sd.ready("calibrated")
    assert sock.recv(1024) == b"READY=1\nSTATUS=calibrated"
    assert sd.watchdog(now=100.0)
    assert not sd.watchdog(now=100.5)  # within a quarter period
    assert sd.watchdog(now=101.0)
    assert sock.recv(1024) == b"WATCHDOG=1" and sock.recv(1024) == b"WATCHDOG=1"
    assert sd.status("60 fps") and sock.recv(1024) == b"STATUS=60 fps"
    assert sd.stopping() and sock.recv(1024) == b"STOPPING=1"
    assert sd.sent == 5
    sd.close()
    sd.close()


def test_notifier_disabled_and_failing(tmp_path):
    sd = Notifier(env={})
    assert not sd.enabled and not sd.ready() and not sd.watchdog()
    broken = Notifier(env={"NOTIFY_SOCKET": str(tmp_path / "gone.sock"), "WATCHDOG_USEC": "1000"})
    assert not broken.watchdog(now=1.0) and broken.failed == 1
