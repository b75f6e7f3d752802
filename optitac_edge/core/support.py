"""Neighbour support: a contact needs fibers that bear each other out (issue 37).

A press bends the skin over a patch: the pins of several neighbouring fibers
tilt together. A fiber's own light drifts on its own (a real 61-fiber sensor's
wandered by a few percent over minutes, some four times more than others). So
with ``ContactOptions.support`` a frame has a contact only where some fiber's
(banded) signal reaches the level *and* so do two of its neighbours' (the fibers
within 1.2 pitches; one missing at the rim reads as at rest): the frame's
supported peak

    max_i min(s_i, second largest of s_j over the neighbours j of i)

must reach the on level (the off level while in contact). It is a gate only:
the surface and every contact's moments are the signal's as it is (limiting
the signal itself flattened a sparse array's presses and moved them). A fiber
that darkens alone then makes no contact however far it drifts. On the real
sensor's snapshots this alone put every rest frame of a day below every
press. ``calibrate levels`` adopts it only where held-out presses show it
helps.
"""

from __future__ import annotations

import cv2
import numpy as np

from optitac_edge.core.layout import FiberLayout

#: The most neighbours a fiber has (a hexagonal array's six).
MAX_NEIGHBOURS = 6


def neighbour_table(layout: FiberLayout) -> np.ndarray:
    """Each fiber's neighbours (within 1.2 pitches), shape (N, 6), int32; -1 where a fiber has fewer."""
    table = np.full((layout.n_fibers, MAX_NEIGHBOURS), -1, dtype=np.int32)
    for i, nb in enumerate(layout.neighbours()):
        nearest = nb[np.argsort(np.hypot(*(layout.xy_mm[nb] - layout.xy_mm[i]).T), kind="stable")]
        table[i, :min(nearest.size, MAX_NEIGHBOURS)] = nearest[:MAX_NEIGHBOURS]
    return table


class NeighbourSupport:
    """The supported peak of a signal (:func:`neighbour_table`'s neighbours); allocates nothing per frame.

    Parameters
    ----------
    table : ndarray, shape (N, 6), int32
        Each fiber's neighbours, -1 for none.
    """

    def __init__(self, table: np.ndarray) -> None:
        n = table.shape[0]
        self.table = np.asarray(table, dtype=np.int32)
        self._index = np.where(self.table < 0, n, self.table).astype(np.intp)  # n: a fiber at rest
        self._ext = np.zeros(n + 1, dtype=np.float32)
        self._values = np.zeros((n, MAX_NEIGHBOURS), dtype=np.float32)
        self._sorted = np.zeros_like(self._values)
        self._limited = np.zeros(n, dtype=np.float32)

    def limited(self, signal: np.ndarray) -> np.ndarray:
        """Each fiber's signal limited to its second-strongest neighbour's, shape (N,), float32 (a buffer)."""
        ext = self._ext
        ext[:-1] = signal
        ext.take(self._index, out=self._values)
        cv2.sort(self._values, cv2.SORT_EVERY_ROW | cv2.SORT_DESCENDING, dst=self._sorted)
        return np.minimum(signal, self._sorted[:, 1], out=self._limited)

    def peak(self, signal: np.ndarray) -> float:
        """The frame's supported peak: the largest of :meth:`limited`, as a float32 value."""
        return float(self.limited(signal).max(initial=-np.inf))


def supported(values: np.ndarray, table: np.ndarray) -> np.ndarray:
    """The support of rows of values, shape (F, N) -> (F, N) (offline: the levels' statistic)."""
    v = np.asarray(values, dtype=np.float64)
    ext = np.concatenate([v, np.zeros((v.shape[0], 1))], axis=1)
    nb = ext[:, np.where(table < 0, v.shape[1], table)]  # (F, N, 6)
    second = -np.sort(-nb, axis=2)[:, :, 1]
    return np.minimum(v, second)
