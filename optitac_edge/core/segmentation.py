"""Truncate the surface and split it into contacts; everything after the truncation reads only the
bounding box of the cells above the level.

Each blob (8-connected) of the cells above the truncation level is one
contact, unless the skin's spread joined neighbouring presses at the (low)
noise level: contacts are seeded by the blobs above ``split_fraction`` of the
strongest peak, and when a blob holds more than one seed, every cell above
the truncation level belongs to its nearest seed (a blob without a seed, a
weaker separate press, is a seed itself; a distance transform with labels).
"""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np

from optitac_edge.core.levels import ContactLevels

#: :meth:`Segmenter.partition`'s label for "all cells above the truncation level" (one blob, one seed).
WHOLE_MASK = -1


class Box(NamedTuple):
    """The bounding box of the cells above the truncation level.

    Attributes
    ----------
    img : ndarray, shape (h, w), float32
        The truncated surface in the box (a contiguous copy: numpy's ufuncs allocate a
        buffer for strided views of the mesh).
    mask : ndarray, shape (h, w), bool
        The cells above the level (a contiguous copy).
    x, y : int
        The box's first mesh column and row.
    peak : float
        The largest value of ``img``.
    """

    img: np.ndarray
    mask: np.ndarray
    x: int
    y: int
    peak: float


class Segmenter:
    """Truncation, bounding box and the multi-contact partition of an (n, n) mesh; preallocated buffers.

    Parameters
    ----------
    n : int
        Mesh size.
    levels : ContactLevels
        The truncation level is read from here at every frame.
    min_cells : float
        Fewest cells of a contact (``min_area_mm2 / cell_area``).
    split_fraction : float
        Seeds are the blobs above this fraction of the strongest peak.
    """

    def __init__(self, n: int, levels: ContactLevels, min_cells: float, split_fraction: float) -> None:
        self.n = n
        self.levels = levels
        self._min_cells = float(min_cells)
        self._split_frac = float(split_fraction)
        n_cells = n * n
        self._mask2d = np.zeros((n, n), dtype=bool)
        self._mask_u8 = self._mask2d.view(np.uint8)
        # bounding-box sized scratch (contiguous (h, w) views at the start, see roi)
        self._split_mask = np.zeros(n_cells, dtype=bool)
        self._blob = np.zeros(n_cells, dtype=bool)
        self._below = np.zeros(n_cells, dtype=bool)
        self._labels = np.zeros(n_cells, dtype=np.int32)
        self._seed_labels = np.zeros(n_cells, dtype=np.int32)
        self._blob_img = np.zeros(n_cells, dtype=np.float32)
        self._nearest_buf = np.zeros(n_cells, dtype=np.int32)
        self._dist = np.zeros(n_cells, dtype=np.float32)
        self._label_values = np.zeros(n_cells, dtype=np.float32)  # labels as float32, for cv2.calcHist
        self._hist = np.zeros(n_cells + 1, dtype=np.float32)
        self._nearest = self.roi(self._nearest_buf, 1, 1)
        self._box_img = np.zeros(n_cells, dtype=np.float32)
        self._box_mask = np.zeros(n_cells, dtype=bool)
        # 0-d operands (a scalar given to a ufunc becomes a new array every call)
        self._zero = np.zeros((), dtype=np.float32)
        self._split = np.zeros((), dtype=np.float32)
        self._label = np.zeros((), dtype=np.int32)

    @staticmethod
    def roi(buffer: np.ndarray, h: int, w: int) -> np.ndarray:
        """A contiguous (h, w) view at the start of a flat (n*n,) buffer."""
        return buffer[:h * w].reshape(h, w)

    def truncate(self, surface: np.ndarray) -> int:
        """Values <= the truncation level become 0, in place (``surface``: shape (n*n,) or (n, n));
        the number of cells above it."""
        img = surface.reshape(self.n, self.n)
        cv2.threshold(img, float(self.levels.trunc), 0.0, cv2.THRESH_TOZERO, dst=img)
        cells = cv2.countNonZero(img)
        if cells:  # the levels are > 0, so "above the level" is "not truncated to 0"
            np.greater(img, self._zero, out=self._mask2d)
        return cells

    def box(self, surface: np.ndarray) -> Box:
        """The bounding box of the cells above the level (after :meth:`truncate` found some)."""
        x, y, w, h = cv2.boundingRect(self._mask_u8)
        img = self.roi(self._box_img, h, w)
        np.copyto(img, surface.reshape(self.n, self.n)[y:y + h, x:x + w])
        mask = self.roi(self._box_mask, h, w)
        np.copyto(mask, self._mask2d[y:y + h, x:x + w])
        return Box(img, mask, x, y, float(cv2.minMaxLoc(img)[1]))

    def partition(self, box: Box, cells: int) -> list[tuple[int, int]]:
        """Split the box into contacts: ``(label, cells)`` of each, largest first, at least ``min_cells``.

        One blob holding one seed is ``[(WHOLE_MASK, cells)]``; otherwise each
        label is a seed of :meth:`contact_surface`. The cells are counted per
        label with ``cv2.calcHist`` over the mask, into preallocated buffers:
        no numpy buffer is allocated per frame.
        """
        img, mask = box.img, box.mask
        h, w = img.shape
        split = max(float(self.levels.trunc), self._split_frac * box.peak)
        seeds = self.roi(self._split_mask, h, w)
        self._split.fill(split)
        np.greater(img, self._split, out=seeds)
        labels = self.roi(self._labels, h, w)
        mask_u8 = mask.view(np.uint8)
        n_parts = cv2.connectedComponents(mask_u8, labels=labels, connectivity=8, ltype=cv2.CV_32S)[0]
        n_seeds = cv2.connectedComponents(seeds.view(np.uint8), labels=self.roi(self._seed_labels, h, w),
                                          connectivity=8, ltype=cv2.CV_32S)[0] - 1
        if n_parts == 2 and n_seeds == 1:  # one blob holding one seed: one contact
            return [(WHOLE_MASK, cells)] if cells >= self._min_cells - 1e-9 else []
        seed_cells = self._count(labels, seeds.view(np.uint8), n_parts)  # each blob's seed cells
        if n_seeds == sum(1 for c in seed_cells[1:] if c > 0):  # no blob holds two seeds: every blob is one contact
            self._nearest = labels
            return self._largest_first(labels, mask_u8, n_parts)
        # seeds: the strong blobs, and the truncated blobs without one
        blob = self.roi(self._blob, h, w)
        np.copyto(blob, seeds)
        for k, n_seed_cells in enumerate(seed_cells):
            if k > 0 and n_seed_cells == 0:
                below = self.roi(self._below, h, w)
                self._label.fill(k)
                np.equal(labels, self._label, out=below)
                np.logical_or(blob, below, out=blob)
        below = self.roi(self._below, h, w)
        np.logical_not(blob, out=below)
        self._nearest = nearest = self.roi(self._nearest_buf, h, w)
        cv2.distanceTransformWithLabels(below.view(np.uint8), cv2.DIST_L2, 3, dst=self.roi(self._dist, h, w),
                                        labels=nearest, labelType=cv2.DIST_LABEL_CCOMP)
        return self._largest_first(nearest, mask_u8, int(cv2.minMaxLoc(nearest)[1]) + 1)

    def _largest_first(self, labels: np.ndarray, mask_u8: np.ndarray, n_labels: int) -> list[tuple[int, int]]:
        """``(label, cells)`` of labels 1 .. n_labels - 1 within the mask, largest first, at least ``min_cells``."""
        counts = self._count(labels, mask_u8, n_labels)
        order = sorted(range(1, n_labels), key=lambda k: -counts[k])
        return [(k, int(counts[k])) for k in order if counts[k] >= self._min_cells - 1e-9]

    def _count(self, labels: np.ndarray, where: np.ndarray, n_labels: int) -> list[float]:
        """Cells of each label 0 .. n_labels - 1 of ``labels`` where ``where`` (uint8) is set."""
        values = self.roi(self._label_values, *labels.shape)
        np.copyto(values, labels, casting="unsafe")
        hist = self._hist[:n_labels].reshape(n_labels, 1)
        cv2.calcHist([values], [0], where, [n_labels], [0, n_labels], hist=hist)
        return hist[:, 0].tolist()

    def contact_surface(self, box: Box, label: int) -> tuple[np.ndarray, int, int]:
        """The truncated surface of contact ``label`` of the last :meth:`partition` alone, in its own
        bounding box: ``(img, x, y)`` with ``img`` (h, w) float32 whose first cell is mesh column
        ``x``, row ``y``.

        Everything measured per contact then reads only that box, not the box of all contacts
        (four contacts on a ring: each a quarter of it).
        """
        if label == WHOLE_MASK:
            return box.img, box.x, box.y
        h, w = box.img.shape
        blob = self.roi(self._blob, h, w)
        self._label.fill(label)
        np.equal(self._nearest, self._label, out=blob)
        np.logical_and(blob, box.mask, out=blob)
        blob_u8 = blob.view(np.uint8)
        bx, by, bw, bh = cv2.boundingRect(blob_u8)
        out = self.roi(self._blob_img, bh, bw)
        out.fill(0.0)
        # OpenCV's masked copy: img * blob casts through a buffer, np.copyto(where=) is 6x slower
        cv2.copyTo(box.img[by:by + bh, bx:bx + bw], blob_u8[by:by + bh, bx:bx + bw], dst=out)
        return out, box.x + bx, box.y + by
