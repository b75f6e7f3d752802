"""Folds of presses for the held-out checks of every calibration step.

The frames of one press are not independent (the same indenter, pose and
depth), so a fold holds out whole presses: never a frame whose press is also
in the fit. This is scikit-learn's ``GroupKFold`` (groups sorted by size, each
given to the fold with the fewest rows so far), written in numpy so the
centroid and width steps need no optional package.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np


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
