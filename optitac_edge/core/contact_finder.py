"""Steps 6 and 7 of the pipeline: the surface truncated, split into contacts, each measured, strongest first."""

from __future__ import annotations

import cv2
import numpy as np

from optitac_edge.core.blob import BlobMeasurer
from optitac_edge.core.contact import ContactEstimate
from optitac_edge.core.corrections import ContactCorrector
from optitac_edge.core.levels import ContactLevels
from optitac_edge.core.segmentation import Segmenter

#: Most blobs measured per frame (the largest by area) before the strongest are kept.
MAX_CANDIDATES = 8


class ContactFinder:
    """The contacts of one surface, into a fixed list of estimates (no allocation that outlives a frame).

    Parameters
    ----------
    segmenter : Segmenter
        Truncation, bounding box and the split into blobs (step 6, 7).
    blobs : BlobMeasurer
        Each blob's moments and shape features (step 7).
    levels : ContactLevels
        The on level (a new contact) and the off level (while in contact: hysteresis).
    contacts : list of ContactEstimate
        Where the frame's contacts go, strongest first (the pipeline's, reused every frame).
    max_contacts : int
        Contacts kept per frame (1: the one blob of the whole surface, as the paper).
    cell_area_mm2 : float
        Area of one mesh cell, mm² (a frame's strength and area when no blob is a contact).
    """

    def __init__(self, segmenter: Segmenter, blobs: BlobMeasurer, levels: ContactLevels,
                 contacts: list[ContactEstimate], max_contacts: int, cell_area_mm2: float) -> None:
        self.segmenter = segmenter
        self.blobs = blobs
        self.levels = levels
        self.contacts = contacts
        self._max_contacts = max_contacts
        self._multi = max_contacts > 1
        self._cell_area = float(cell_area_mm2)
        self._cands = [ContactEstimate() for _ in range(MAX_CANDIDATES)]

    def find(self, surface: np.ndarray, est: ContactEstimate, in_contact: bool,
             corrector: ContactCorrector | None, gated: bool = False) -> int:
        """Truncate ``surface`` (shape (n*n,), float32, in place), find and measure its contacts.

        The contacts go to ``contacts[:n]``, strongest first, each corrected by ``corrector`` (None: raw);
        with none, ``est`` says so (with the frame's strength and area above the level when there was some).
        ``gated``: the frame can have no contact (neighbour support, :mod:`optitac_edge.core.support`).
        Returns ``n``.
        """
        seg, blobs = self.segmenter, self.blobs
        cells = seg.truncate(surface)
        if cells == 0:
            est.clear()
            return 0
        level = np.float32(np.inf) if gated else (self.levels.off if in_contact else self.levels.on)
        # everything below reads only the bounding box of the cells above the truncation level
        box = seg.box(surface)
        n_cand = 0
        if not self._multi:
            n_cand = int(blobs.measure(box.img, box.peak, cells, level, self._cands[0], box.x, box.y))
        else:
            for k, blob_cells in seg.partition(box, cells):
                img, x, y = seg.contact_surface(box, k)  # the contact's own box
                peak = box.peak if img is box.img else cv2.minMaxLoc(img)[1]
                n_cand += blobs.measure(img, peak, blob_cells, level, self._cands[n_cand], x, y)
                if n_cand == MAX_CANDIDATES:
                    break
        if n_cand == 0:
            est.clear(float(cv2.sumElems(box.img)[0]) * self._cell_area, cells * self._cell_area)
            return 0
        cands = self._cands
        # strongest first, ties in candidate order (a stable sort; Python's: no numpy buffer)
        ranked = sorted(range(n_cand), key=lambda i: -cands[i].strength) if n_cand > 1 else range(1)
        n = min(n_cand, self._max_contacts)
        for i in range(n):
            c = self.contacts[i]
            c.assign(cands[ranked[i]])
            if corrector is not None:
                corrector.apply(c)
        return n
