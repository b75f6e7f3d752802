"""Contact levels chosen on held-out presses (``calibrate levels``), pure numpy.

Every scored frame of the user's recordings (each with its own baseline: its
rest frames and tare points) gives each fiber's signal ``s_i``. The rest frames
give each fiber's *rest excursion* (the RMS of its signal at rest); the part
of it its frame-to-frame noise explains (``calibrate fibers``' noise in gray
levels over the fiber's light) taken out, what is left is its **drift** since
the baseline (:func:`fiber_drift`). Noise and drift together give each fiber's
excursion ``e_i`` and its excess ``x_i`` (:mod:`optitac_edge.core.levels`).
With bands ``on * x_i`` a frame reaches the on level ``L`` where some fiber has
``s_i - L x_i >= L``, i.e. where its statistic

    z = max_i s_i / (1 + x_i)

is at least ``L``. So the on level is a threshold on one number per frame:
:func:`choose_level` puts it where rest frames and contact frames are best
told apart (the least balanced error, the middle of the widest such gap), and
:func:`held_out_levels` says how that choice does on presses and rest frames it
was not made on (folds that never split a press, the rest frames in runs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from optitac_edge.calibration.folds import MAX_FOLDS, stratified_group_folds
from optitac_edge.core.levels import fiber_excess
from optitac_edge.core.support import supported

#: The smallest statistic a level is chosen among (relative units): below it a fiber's light is noise in
#: the camera's last bit.
LEVEL_FLOOR = 1e-3


def fiber_drift(rest_signals: np.ndarray, noise_part: np.ndarray | None) -> np.ndarray:
    """Each fiber's drift since the baseline, relative units, shape (N,): the RMS of its signal over rest frames
    with the part its frame-to-frame noise explains taken out, ``sqrt(max(mean(s^2) - mean(n^2), 0))``.

    Parameters
    ----------
    rest_signals : ndarray, shape (R, N)
        The rest frames' signals (relative units).
    noise_part : ndarray, shape (R, N), or None
        Each of those frames' expected squared noise, ``(noise_gray / light)^2 (1 + 1 / baseline frames)``
        (None: no noise figure; the drift is the whole excursion).
    """
    total = np.mean(np.square(np.asarray(rest_signals, dtype=np.float64)), axis=0)
    if noise_part is not None:
        total = total - np.mean(np.asarray(noise_part, dtype=np.float64), axis=0)
    return np.sqrt(np.maximum(total, 0.0))


def excursion_of(drift: np.ndarray, noise_part: np.ndarray | None) -> np.ndarray:
    """Each fiber's rest excursion from its drift and its frames' mean squared noise, shape (N,)."""
    e2 = np.square(np.asarray(drift, dtype=np.float64))
    if noise_part is not None:
        e2 = e2 + np.mean(np.asarray(noise_part, dtype=np.float64), axis=0)
    return np.sqrt(e2)


def frame_statistic(signals: np.ndarray, excess: np.ndarray | None, live: np.ndarray,
                    support: np.ndarray | None = None) -> np.ndarray:
    """Each frame's ``z = max_i s_i / (1 + x_i)`` over the live fibers, shape (F,); with neighbour support
    (:mod:`optitac_edge.core.support`) of ``s / (1 + x)``: the band and the support commute at the on level.

    Parameters
    ----------
    signals : ndarray, shape (F, N)
    excess : ndarray, shape (N,), or None
        Each fiber's excess (None: none has a band).
    live : ndarray of bool, shape (N,)
    support : ndarray, shape (N, 6), int, optional
        Each fiber's neighbours (-1: none): the frames' values with neighbour support.
    """
    s = np.asarray(signals, dtype=np.float64)
    if excess is not None:
        s = s / (1.0 + np.asarray(excess, dtype=np.float64))
    alive = np.asarray(live, dtype=bool)
    s = np.where(alive, s, 0.0)  # a dead fiber's signal is 0
    if support is not None:
        s = supported(s, support)
    s = s[:, alive]
    return s.max(axis=1) if s.shape[1] else np.zeros(s.shape[0])


def choose_level(rest: np.ndarray, contact: np.ndarray, floor: float = LEVEL_FLOOR) -> float:
    """The on level that best tells rest frames (statistics ``rest``) from contact frames (``contact``).

    Among the levels between two neighbouring statistics, those with the least balanced error (the fraction
    of contact frames below the level plus the fraction of rest frames at or above it) are taken, and of them
    the widest gap (in ratio); the level is its geometric middle: the most room either way where the two
    kinds of frame are told apart. Statistics below ``floor`` count as ``floor``.

    Raises
    ------
    ValueError
        Without rest frames or without contact frames.
    """
    r = np.maximum(np.asarray(rest, dtype=np.float64), floor)
    c = np.maximum(np.asarray(contact, dtype=np.float64), floor)
    if not r.size or not c.size:
        raise ValueError("choosing a level needs rest frames and contact frames")
    values = np.unique(np.concatenate([r, c]))
    # the gaps: below the smallest value, between each pair, above the largest
    lows = np.concatenate([[values[0] / 2.0], values])
    highs = np.concatenate([values, [values[-1] * 2.0]])
    levels = np.sqrt(lows * highs)  # a level strictly inside each gap
    rs, cs = np.sort(r), np.sort(c)
    missed = np.searchsorted(cs, levels, side="left") / cs.size  # contact frames below the level
    false = 1.0 - np.searchsorted(rs, levels, side="left") / rs.size  # rest frames at or above it
    error = missed + false
    best = np.flatnonzero(error <= error.min() + 1e-12)
    widest = best[np.argmax(np.log(highs[best]) - np.log(lows[best]))]
    return float(levels[widest])


@dataclass(frozen=True)
class HeldOutLevels:
    """How levels chosen without some frames do on them.

    Attributes
    ----------
    detection, false_rate : float
        Fraction of held-out contact frames found; of held-out rest frames with a contact (the statistic
        against the fold's level).
    contact_frames, rest_frames, folds : int
    levels : tuple of float
        Each fold's on level.
    margin : float
        How far apart the held-out frames' statistics are, in units of each fold's level:
        ``ln(p10 of contact frames' / p90 of rest frames')`` (larger: the choice holds with more room).
    """

    detection: float
    false_rate: float
    contact_frames: int
    rest_frames: int
    folds: int
    levels: tuple[float, ...]
    margin: float = 0.0


def rest_runs(is_contact: np.ndarray, session: np.ndarray, frame: np.ndarray, t_ns: np.ndarray,
              gap_ns: int) -> np.ndarray:
    """A group for every row: rest rows in runs -- consecutive frames of one session, no more than ``gap_ns``
    apart (snapshots further apart are runs of their own) -- numbered -1, -2, ...; contact rows 0.

    Parameters
    ----------
    is_contact, session, frame, t_ns : ndarray, shape (F,)
        Each row's kind, recording, frame number and time.
    """
    groups = np.zeros(is_contact.size, dtype=np.int64)
    run = 0
    for k in range(is_contact.size):
        if is_contact[k]:
            continue
        if (k == 0 or is_contact[k - 1] or session[k] != session[k - 1] or frame[k] != frame[k - 1] + 1
                or t_ns[k] - t_ns[k - 1] > gap_ns):
            run += 1
        groups[k] = -run
    return groups


def held_out_levels(signals: np.ndarray, noise_part: np.ndarray | None, is_contact: np.ndarray,
                    groups: np.ndarray, live: np.ndarray, seed: int = 0,
                    support: np.ndarray | None = None) -> HeldOutLevels:
    """Levels chosen fold by fold (each fiber's drift and the level from the other folds' frames), scored on
    the fold's own frames.

    Parameters
    ----------
    signals : ndarray, shape (F, N)
        Every scored frame's signal.
    noise_part : ndarray, shape (F, N), or None
        Every frame's expected squared noise per fiber (see :func:`fiber_drift`).
    is_contact : ndarray of bool, shape (F,)
    groups : ndarray, shape (F,)
        A press's frames share a group, and so do a run of rest frames (:func:`rest_runs`); a fold never
        splits a group.
    live : ndarray of bool, shape (N,)
    support : ndarray, shape (N, 6), optional
        Each fiber's neighbours: the statistic with neighbour support.

    Raises
    ------
    ValueError
        With fewer than two groups of rest frames or of presses.
    """
    y = np.asarray(is_contact, dtype=np.int64)
    n_rest_groups = np.unique(groups[y == 0]).size
    n_press = np.unique(groups[y == 1]).size
    folds = min(MAX_FOLDS, n_rest_groups, n_press)
    if folds < 2:
        raise ValueError(f"need 2 runs of rest frames and 2 presses or more to choose levels on held-out "
                         f"frames, got {n_rest_groups} and {n_press}")
    found = false = 0
    levels = []
    rel_contact, rel_rest = [], []
    for test in stratified_group_folds(y, groups, folds, np.random.default_rng(seed)):
        train = np.setdiff1d(np.arange(y.size), test)
        rest_train = train[y[train] == 0]
        part = None if noise_part is None else noise_part[rest_train]
        excursion = excursion_of(fiber_drift(signals[rest_train], part), part)
        excess = fiber_excess(excursion, live, rest_train.size)
        z = frame_statistic(signals, excess, live, support)
        level = choose_level(z[rest_train], z[train[y[train] == 1]])
        levels.append(level)
        found += int(np.count_nonzero(z[test[y[test] == 1]] >= level))
        false += int(np.count_nonzero(z[test[y[test] == 0]] >= level))
        rel_contact.append(np.maximum(z[test[y[test] == 1]], LEVEL_FLOOR) / level)
        rel_rest.append(np.maximum(z[test[y[test] == 0]], LEVEL_FLOOR) / level)
    n_contact, n_rest = int(y.sum()), int((y == 0).sum())
    margin = math.log(float(np.percentile(np.concatenate(rel_contact), 10))
                      / float(np.percentile(np.concatenate(rel_rest), 90)))
    return HeldOutLevels(found / n_contact, false / n_rest, n_contact, n_rest, folds, tuple(levels), margin)


def spread(values: np.ndarray) -> dict[str, float]:
    """Median, 90th percentile and largest of ``values`` (rounded), for a summary."""
    v = np.asarray(values, dtype=np.float64)
    if not v.size:
        return {"median": math.nan, "p90": math.nan, "max": math.nan}
    return {"median": round(float(np.median(v)), 5), "p90": round(float(np.percentile(v, 90)), 5),
            "max": round(float(v.max()), 5)}
