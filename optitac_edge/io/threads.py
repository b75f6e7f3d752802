"""Threads named where the operating system shows them (``top -H``, ``ps -L``, ``/proc/PID/task/*/comm``)."""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
import threading
from functools import cache

#: ``prctl`` option that names the calling thread (linux/prctl.h).
PR_SET_NAME = 15
#: The kernel keeps 15 bytes of a thread's name.
MAX_NAME_BYTES = 15


@cache
def _prctl() -> ctypes._NamedFuncPointer | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    except OSError:
        return None
    return libc.prctl


def name_this_thread(name: str) -> bool:
    """Give the calling thread ``name`` (its first 15 bytes) in the operating system; False where it cannot.

    Python's ``threading.Thread(name=...)`` names a thread for Python only (before 3.14); a board's
    operator reads ``top -H`` and the harness of docs/performance.md reads ``/proc``, so every thread
    the service starts names itself first.
    """
    prctl = _prctl()
    if prctl is None:
        return False
    return prctl(PR_SET_NAME, name.encode()[:MAX_NAME_BYTES], 0, 0, 0) == 0


class NamedThread(threading.Thread):
    """A :class:`threading.Thread` that gives itself its ``name`` in the operating system before it runs
    (:func:`name_this_thread`): every thread the service starts is one."""

    def run(self) -> None:
        name_this_thread(self.name)
        super().run()
