"""Work a signal must not cut short (a rig's retract): the first SIGINT, SIGTERM or SIGHUP that comes meanwhile
is held until it is done; a second stops it.

The command line's signal handler (:func:`optitac_edge.cli`'s) asks :func:`hold` before it raises: inside
:func:`deferred` the first signal is kept (``held``) and the handler returns; a second is raised as usual.
The caller decides what a held signal means once the work is done (a collection that ends anyway after an
error says it in its one line).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

#: Signals held by the innermost :func:`deferred` block (at most one), and how many blocks are open.
_held: list[int] = []
_depth = [0]


@contextmanager
def deferred() -> Iterator[list[int]]:
    """Hold the first signal while the block runs; yields the list that receives it (empty: none came)."""
    _depth[0] += 1
    mine: list[int] = []
    outer = _held[:]
    _held.clear()
    try:
        yield mine
    finally:
        mine.extend(_held)
        _held[:] = outer
        _depth[0] -= 1


def hold(signum: int) -> bool:
    """For a signal handler: True when ``signum`` is held (inside :func:`deferred`, the first to come);
    False when the handler acts on it (outside, or a second signal)."""
    if _depth[0] > 0 and not _held:
        _held.append(signum)
        return True
    return False
