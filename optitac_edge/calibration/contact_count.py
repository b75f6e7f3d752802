"""How many contacts a frame: the calibration presses read with several and with one, compared.

On a real skin a press tilts the pins over a patch wider than a pitch, and the fibers around it darken and
brighten unevenly (a real 61-fiber, 4 mm-pitch sensor's presses of 1-7 N): its truncated surface can split
into pieces, and the strongest piece is then reported as the press, a pitch or more from it. Read as one
contact a frame (the whole truncated surface: the paper's moments) the pieces are weighed together.
``calibrate centroid`` adopts that only where its presses show it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from optitac_edge.calibration.evaluation import detected_rows, press_ids
from optitac_edge.calibration.measure import Measurements
from optitac_edge.io.recording import Truth

#: ``calibrate centroid`` reads the presses as one contact a frame when that places them better than the
#: configured several by more than this many standard errors of the per-press difference (one-sided, about
#: 2 %): a sensor that shows no sign of it keeps its several contacts.
ONE_CONTACT_SE = 2.0


@dataclass(frozen=True)
class OneContactEvidence:
    """The calibration presses read with several contacts a frame and with one: RMS location error (mm) of
    the presses both detect, and whether one contact a frame is adopted."""

    several_rms_mm: float
    one_rms_mm: float
    adopt: bool


def one_contact_evidence(several: Measurements, one: Measurements, truth: Truth) -> OneContactEvidence:
    """Whether the presses are placed better read as one contact a frame than as several.

    One contact a frame is adopted where the per-press difference of squared errors (several minus one, each press's frames averaged) exceeds :data:`ONE_CONTACT_SE` standard
    errors over at least three presses; with no such evidence the configured count stays.
    """
    rows = np.flatnonzero(detected_rows(several, truth) & detected_rows(one, truth))
    if rows.size == 0:
        return OneContactEvidence(math.nan, math.nan, False)
    frames, true = truth.frame[rows], np.stack([truth.x_mm[rows], truth.y_mm[rows]], axis=1)
    press = np.unique(press_ids(truth)[rows], return_inverse=True)[1].ravel()

    def per_press(m: Measurements) -> np.ndarray:
        squared = (m.x_mm[frames] - true[:, 0]) ** 2 + (m.y_mm[frames] - true[:, 1]) ** 2
        return np.bincount(press, squared) / np.bincount(press)

    a, b = per_press(several), per_press(one)
    gain = a - b
    adopt = False
    if gain.size >= 3:
        se = float(np.std(gain, ddof=1) / math.sqrt(gain.size))
        adopt = bool(gain.mean() > ONE_CONTACT_SE * se) and se > 0.0
    return OneContactEvidence(float(np.sqrt(a.mean())), float(np.sqrt(b.mean())), adopt)
