"""One copy of a read-only table for every pipeline of the process that has the same one.

The patches of a hand cut from one design have the same fiber layout, so the same surface operator: the same
gradient solve's factor and the same triangles, which the compiled kernel reads every frame. Six patches kept
six copies (~120 KB each) and their tables together outgrew a Raspberry Pi 4's 1 MB L2; shared, the cache holds
one (docs/performance.md, "Working set per sensor").
"""

from __future__ import annotations

import hashlib
import threading
import weakref
from collections.abc import Mapping

import numpy as np

_Key = tuple[str, tuple[int, ...], bytes]
#: The tables handed out, by (dtype, shape, digest of the bytes); an entry goes with its last user.
_TABLES: weakref.WeakValueDictionary[_Key, np.ndarray] = weakref.WeakValueDictionary()
_LOCK = threading.Lock()


def shared_table(table: np.ndarray) -> np.ndarray:
    """The read-only table equal to ``table`` (dtype, shape and every byte) that this process already shares,
    or a read-only copy of ``table``, shared from now on.

    Parameters
    ----------
    table : ndarray
        Any array; it is not changed.

    Returns
    -------
    ndarray
        C-contiguous, read-only, equal to ``table``.
    """
    data = np.ascontiguousarray(table)
    key = (data.dtype.str, data.shape, hashlib.blake2b(data.tobytes(), digest_size=16).digest())
    with _LOCK:
        found = _TABLES.get(key)
        if found is not None and np.array_equal(found, data):  # the digest picks it; the bytes decide
            return found
        copy = data.copy()
        copy.setflags(write=False)
        _TABLES[key] = copy
        return copy


def shared_tables(tables: Mapping[str, np.ndarray | int | float]) -> dict[str, np.ndarray | int | float]:
    """``tables`` with every array replaced by its :func:`shared_table` (numbers as they are)."""
    return {name: shared_table(v) if isinstance(v, np.ndarray) else v for name, v in tables.items()}
