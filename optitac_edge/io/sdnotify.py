"""systemd's notification protocol (sd_notify) in a few lines, without libsystemd.

Under ``Type=notify`` systemd sets ``$NOTIFY_SOCKET``; the service sends
``READY=1`` once it works (after the first processed frame), ``WATCHDOG=1`` at
least every half ``WatchdogSec`` (from the frame loop itself, so a stuck loop
gets the service restarted), ``STATUS=...`` for ``systemctl status`` and
``STOPPING=1`` on the way out. Outside systemd every call is a no-op.
Nothing here ever raises: a failed notification returns False.
"""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Mapping


def _address(env: Mapping[str, str]) -> str | bytes | None:
    path = env.get("NOTIFY_SOCKET", "")
    if not path:
        return None
    if path.startswith("@"):  # abstract namespace
        return b"\0" + path[1:].encode()
    if path.startswith("/"):
        return path
    return None  # vsock:... and other forms are not for a local service


def watchdog_period(env: Mapping[str, str] | None = None) -> float | None:
    """systemd's watchdog timeout in seconds (``$WATCHDOG_USEC``), None when not enabled for us."""
    env = os.environ if env is None else env
    try:
        usec = int(env.get("WATCHDOG_USEC", ""))
    except ValueError:
        return None
    pid = env.get("WATCHDOG_PID", "")
    if pid:
        try:
            if int(pid) != os.getpid():
                return None
        except ValueError:
            return None
    return usec / 1e6 if usec > 0 else None


class Notifier:
    """One service's notifications, keeping one socket and rate-limiting the watchdog.

    >>> sd = Notifier()            # doctest: +SKIP
    >>> sd.ready()                 # after the first processed frame
    >>> sd.watchdog()              # every frame; sends at most every period/4
    >>> sd.stopping()
    """

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        self._address = _address(env)
        period = watchdog_period(env)
        self.watchdog_interval_s = period / 4.0 if period else None
        self._last_kick = -float("inf")
        self._sock: socket.socket | None = None
        self.sent = 0
        self.failed = 0

    @property
    def enabled(self) -> bool:
        return self._address is not None

    def send(self, state: str) -> bool:
        if self._address is None:
            return False
        try:
            if self._sock is None:
                self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._sock.sendto(state.encode(), self._address)
            self.sent += 1
            return True
        except Exception:  # noqa: BLE001
            self.failed += 1
            return False

    def ready(self, status: str | None = None) -> bool:
        return self.send("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def status(self, text: str) -> bool:
        return self.send(f"STATUS={text}")

    def watchdog(self, now: float | None = None) -> bool:
        """Kick the watchdog if enabled and at least a quarter period has passed."""
        if self.watchdog_interval_s is None:
            return False
        now = time.monotonic() if now is None else now
        if now - self._last_kick < self.watchdog_interval_s:
            return False
        self._last_kick = now
        return self.send("WATCHDOG=1")

    def stopping(self) -> bool:
        return self.send("STOPPING=1")

    def close(self) -> None:
        if self._sock is not None:
            try:
                self._sock.close()
            finally:
                self._sock = None


__all__ = ["Notifier", "watchdog_period"]
