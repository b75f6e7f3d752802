"""Reading a ``.npz`` file (a bundle, a recording's fiber pixel groups) without trusting its sizes.

A member's ``.npy`` header says how much its data takes; a member over the
file's limit, members over its total, too many members or an object dtype are
refused before a byte of data is allocated or decompressed (the zip
directory's sizes can lie; the header is what numpy would allocate: a 1.2 MB
file may inflate to gigabytes).
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from optitac_edge.errors import OptiTacError


@dataclass(frozen=True)
class NpzLimits:
    """What one kind of ``.npz`` may hold: its name for the lines, bytes a member, bytes in all, members."""

    what: str
    member_bytes: int
    total_bytes: int
    members: int


def read_npz_members(path: Path, limits: NpzLimits, error: type[OptiTacError]) -> dict[str, np.ndarray]:
    """Every member of the ``.npz`` at ``path``, each checked against ``limits`` before it is read.

    Raises
    ------
    error
        One line naming the file and what is wrong (``zipfile`` and numpy errors propagate for the
        caller's own line: a truncated or flipped file).
    """
    with zipfile.ZipFile(path) as zf:
        names = [n for n in zf.namelist() if n.endswith(".npy")]
        if len(names) > limits.members or len(names) != len(zf.namelist()):
            raise error(f"{path}: not a {limits.what} ({len(zf.namelist())} members)")
        total = 0
        for name in names:
            with zf.open(name) as f:
                version = np.lib.format.read_magic(f)
                if version == (1, 0):
                    shape, _fortran, dtype = np.lib.format.read_array_header_1_0(f, max_header_size=10_000)
                elif version == (2, 0):
                    shape, _fortran, dtype = np.lib.format.read_array_header_2_0(f, max_header_size=10_000)
                else:
                    raise error(f"{path}: member {name[:-4]!r} in .npy format {version}, not 1.0 or 2.0")
            if dtype.hasobject:
                raise error(f"{path}: member {name[:-4]!r} holds Python objects")
            nbytes = int(np.prod(shape, dtype=np.float64)) * dtype.itemsize
            total += nbytes
            if nbytes > limits.member_bytes or total > limits.total_bytes:
                raise error(f"{path}: member {name[:-4]!r} claims {nbytes / 2**20:.0f} MiB "
                            f"(a {limits.what} holds at most {limits.member_bytes >> 20} MiB a member, "
                            f"{limits.total_bytes >> 20} MiB in all)")
        members = {}
        for name in names:
            with zf.open(name) as f:
                members[name[:-4]] = np.lib.format.read_array(f, allow_pickle=False)
    return members
