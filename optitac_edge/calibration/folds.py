"""Folds of presses for the held-out checks of every calibration step.

The frames of one press are not independent (the same indenter, pose and
depth), so a fold holds out whole presses: never a frame whose press is also
in the fit. This is scikit-learn's ``GroupKFold`` (groups sorted by size, each
given to the fold with the fewest rows so far), written in numpy so the
centroid and width steps need no optional package. The shape classifier's
selection uses folds that are also stratified by class
(:func:`stratified_group_split`, :func:`stratified_group_folds`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

#: Folds of every held-out check (fewer with fewer presses).
MAX_FOLDS = 8


def press_folds(groups: np.ndarray, n_splits: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """``(train, test)`` row indices for each of ``n_splits`` folds; a group is never split.

    Parameters
    ----------
    groups : ndarray, shape (K,)
        The press (any hashable label) of every row.
    n_splits : int
        Number of folds, 2 <= n_splits <= the number of groups.

    Raises
    ------
    ValueError
        If ``n_splits`` is out of that range.
    """
    keys, inverse, counts = np.unique(np.asarray(groups), return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    if not 2 <= n_splits <= keys.size:
        raise ValueError(f"need 2 to {keys.size} folds for {keys.size} presses, got {n_splits}")
    fold_of_group = np.empty(keys.size, dtype=np.int64)
    rows = np.zeros(n_splits, dtype=np.int64)
    for g in np.argsort(-counts, kind="stable"):  # largest first, each to the emptiest fold
        f = int(np.argmin(rows))
        fold_of_group[g] = f
        rows[f] += counts[g]
    fold = fold_of_group[inverse]
    for f in range(n_splits):
        yield np.flatnonzero(fold != f), np.flatnonzero(fold == f)


def fold_count(groups: np.ndarray, min_presses: int, what: str) -> int:
    """How many folds the presses ``groups`` make (at most :data:`MAX_FOLDS`).

    Raises
    ------
    ValueError
        With fewer than ``min_presses`` presses: ``need N presses or more to {what} on held-out presses``.
    """
    n_groups = np.unique(groups).size
    if n_groups < min_presses:
        raise ValueError(f"need {min_presses} presses or more to {what} on held-out presses, got {n_groups}")
    return min(MAX_FOLDS, n_groups)


@dataclass(frozen=True, eq=False)
class HeldOut:
    """Errors of rows predicted by fits that never saw their press.

    Attributes
    ----------
    errors : ndarray, shape (K,) or (K, M)
        Every held-out row's error (prediction − truth), fold by fold.
    fold_rmse : ndarray, shape (folds,)
        Each fold's RMSE over all its errors.
    """

    errors: np.ndarray
    fold_rmse: np.ndarray

    @property
    def rmse(self) -> np.ndarray:
        """RMSE pooled over the folds, per column (a 0-d array for one)."""
        return np.sqrt(np.mean(self.errors ** 2, axis=0))

    @property
    def spread(self) -> float:
        """Standard deviation of the folds' RMSEs."""
        return float(np.std(self.fold_rmse))


def held_out_errors(groups: np.ndarray, folds: int, error: Callable[[np.ndarray, np.ndarray], np.ndarray]
                    ) -> HeldOut:
    """``error(train, test)`` (a fit on rows ``train``, its errors on rows ``test``) over :func:`press_folds`.

    Exceptions of ``error`` (a fold that cannot be fitted) pass through.
    """
    errors, fold_rmse = [], []
    for train, test in press_folds(groups, folds):
        err = np.asarray(error(train, test), dtype=np.float64)
        errors.append(err)
        fold_rmse.append(float(np.sqrt(np.mean(err ** 2))))
    return HeldOut(np.concatenate(errors), np.array(fold_rmse))


def _group_labels(y: np.ndarray, groups: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unique groups, each group's majority class, and each row's group index."""
    ug, inv = np.unique(groups, return_inverse=True)
    counts = np.zeros((ug.size, int(y.max()) + 1), dtype=np.int64)
    np.add.at(counts, (inv, y), 1)
    return ug, counts.argmax(axis=1), inv


def stratified_group_split(
    y: np.ndarray, groups: np.ndarray, fraction: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Rows of about ``fraction`` of each class's groups vs the rest.

    Parameters
    ----------
    y : ndarray, shape (n,), int
        Class indices.
    groups : ndarray, shape (n,)
        Press ids.
    fraction : float
    rng : numpy Generator

    Returns
    -------
    rest, held : ndarray, int64
        Disjoint sorted row indices; every class with >= 2 groups has at least
        one group on each side.
    """
    ug, gcls, inv = _group_labels(y, groups)
    held_g = np.zeros(ug.size, dtype=bool)
    for c in np.unique(gcls):
        g = rng.permutation(np.flatnonzero(gcls == c))
        k = round(fraction * g.size)
        if g.size >= 2:
            k = min(max(k, 1), g.size - 1)
        held_g[g[:k]] = True
    held = held_g[inv]
    return np.flatnonzero(~held), np.flatnonzero(held)


def stratified_group_folds(
    y: np.ndarray, groups: np.ndarray, k: int, rng: np.random.Generator
) -> list[np.ndarray]:
    """Grouped, stratified folds: each class's groups shuffled and dealt round-robin.

    Returns
    -------
    list of ndarray, int64
        ``k`` disjoint sets of row indices (the held-out rows of each fold).
    """
    ug, gcls, inv = _group_labels(y, groups)
    fold_g = np.empty(ug.size, dtype=np.int64)
    for c in np.unique(gcls):
        g = rng.permutation(np.flatnonzero(gcls == c))
        fold_g[g] = np.arange(g.size) % k
    fold = fold_g[inv]
    return [np.flatnonzero(fold == i) for i in range(k)]
